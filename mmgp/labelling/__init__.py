"""Labelling every sample: the stochastic EM over per-mode GPs with a disturbance mode
(``sem``, its ``settings``, ``estep``, ``mstep``, ``convergence``), the HMM it and the diagnosis
share (``hmm``), the push scan (``scan``), the friction check (``dissipation``), the GP inputs
built from logs (``features``) and the training report (``report``)."""
