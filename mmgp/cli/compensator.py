"""Commands for the exported feedforward compensator: export, check-passivity."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from .common import _fail, app, force_option, seed_option


@app.command()
def export(model_dir: Path = typer.Argument(..., help="Folder written by 'mmgp train'."),
           out: Path = typer.Option(..., "--out", help="Compensator file (.json or .npz)."),
           c_source: Optional[Path] = typer.Option(None, "--c", help="Also write C source+header with this prefix."),
           config: Optional[Path] = typer.Option(None, "--config", help="YAML settings, section 'export'."),
           max_support: Optional[int] = typer.Option(None, "--max-support", help="Support positions (default 1000)."),
           force: bool = force_option()):
    """Export the position-only passive feedforward tau_ff(q) = grad V(q) with its storage function."""
    from ..compensator import check_passivity
    from ..config import load_settings
    from ..estimator import MultimodalGP

    try:
        if out.exists() and not force:
            raise InputError("output exists (use --force to replace it)", file=out)
        settings = load_settings(config, "export", MultimodalGP.to_compensator, max_support=max_support)
        comp = MultimodalGP.load(model_dir).to_compensator(**settings)
        comp.save(out)
        written = [str(out)]
        if c_source is not None:
            written += [str(p) for p in comp.write_c(c_source)]
        chk = check_passivity(comp)
    except InputError as exc:
        _fail(exc)
    typer.echo(f"wrote {', '.join(written)}; passivity check {'passed' if chk['passed'] else 'FAILED'}")


@app.command("check-passivity")
def check_passivity_cmd(file: Path = typer.Argument(..., help="Compensator file from 'mmgp export'."),
                        n_configs: int = typer.Option(200, "--configs", help="Random configurations at which "
                                                      "the gradient of the storage is checked."),
                        n_loops: int = typer.Option(50, "--loops", help="Random closed loops around which "
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
