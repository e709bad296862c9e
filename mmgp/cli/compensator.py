"""Commands for the exported feedforward compensator: export, check-passivity."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError, describe
from .common import _fail, _model_files, app, config_option, force_option, seed_option, setting_option


def _still_joints(model) -> list[str]:
    """Joints whose nominal-mode positions never change: a position-only field has nothing to fit there."""
    import numpy as np

    q = np.asarray(model.support_q_, dtype=np.float64)
    span = q.max(axis=0) - q.min(axis=0)
    return [name for name, s in zip(model.joint_names_, span) if not s > 1e-9 * max(1.0, float(np.abs(q).max()))]


def _build(model_dir: Path, settings: dict):
    """The compensator of the model in ``model_dir``; a model it cannot be built from is an InputError."""
    from ..estimator import MultimodalGP
    from ..gp.linalg import GPNumericalError

    model = MultimodalGP.load(model_dir)
    still = _still_joints(model)
    if still:
        raise InputError(f"joint(s) {still} never move in the training data: a position-only feedforward "
                         "cannot be learned for them (train on a log that moves every joint)", file=model_dir)
    try:
        return model.to_compensator(**settings)
    except (GPNumericalError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"cannot build the compensator ({describe(exc)})", file=model_dir) from None


@app.command()
def export(model_dir: Path = typer.Argument(..., help="Folder written by 'mmgp train'."),
           out: Path = typer.Option(..., "--out", help="Compensator file (.json or .npz)."),
           c_source: Optional[Path] = typer.Option(None, "--c", help="Also write C source+header with this prefix."),
           config: Optional[Path] = config_option("export"),
           max_support: Optional[int] = setting_option("export", "max_support", "--max-support",
                                                       help="Support positions."),
           force: bool = force_option()):
    """Export the position-only passive feedforward tau_ff(q) = grad V(q) with its storage function;
    a field that fails the passivity check is not written (exit status 1)."""
    from ..compensator import check_passivity
    from ..config import load_settings
    from ..data.outputs import check_output
    from ..estimator import MultimodalGP

    try:
        check_output(out, force=force, inputs=_model_files(model_dir))
        settings = load_settings(config, "export", MultimodalGP.to_compensator, max_support=max_support)
        comp = _build(model_dir, settings)
        chk = check_passivity(comp)
        if not chk["passed"]:
            typer.echo(f"error: file {model_dir}: the exported field fails the passivity check "
                       f"(gradient error {chk['grad_max_rel_err']:.3g}, loop work {chk['loop_max_rel_work']:.3g}, "
                       f"storage bounded below: {chk['storage_bounded_pass']}); nothing written", err=True)
            raise typer.Exit(1)
        comp.save(out)
        written = [str(out)]
        if c_source is not None:
            written += [str(p) for p in comp.write_c(c_source)]
    except InputError as exc:
        _fail(exc)
    typer.echo(f"wrote {', '.join(written)}; passivity check passed")


@app.command("check-passivity")
def check_passivity_cmd(file: Path = typer.Argument(..., help="Compensator file from 'mmgp export'."),
                        n_configs: int = typer.Option(200, "--configs", min=1, help="Random configurations at which "
                                                      "the gradient of the storage is checked."),
                        n_loops: int = typer.Option(50, "--loops", min=1, help="Random closed loops around which "
                                                    "the work must be zero."),
                        seed: int = seed_option(0)):
    """Numerically confirm grad S = tau_ff, zero work around closed loops, S bounded below."""
    from ..compensator import check_passivity, load_compensator

    try:
        comp = load_compensator(file)
    except (InputError, ValueError, OSError) as exc:
        _fail(exc)
    res = check_passivity(comp, n_configs=n_configs, n_loops=n_loops, seed=seed)
    for k, v in res.items():
        if not isinstance(v, (dict, list)):
            typer.echo(f"{k}: {v}")
    if not res["passed"]:
        raise typer.Exit(1)
