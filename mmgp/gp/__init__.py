"""Gaussian processes in float64 torch: ``linalg`` (robust Cholesky, devices, threads), ``kernels``
(batched RBF), ``objectives`` (leave-one-out, marginal likelihood, leave-block-out), ``hyper`` (the
one hyperparameter optimiser), ``exact`` and ``sparse`` (RBF regression), ``windowed``
(leave-window-out predictions) and ``gradient_field`` (GPs whose mean is a gradient)."""
