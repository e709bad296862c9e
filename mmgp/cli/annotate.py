"""``mmgp annotate``: a robot recording with mmgp's labels added as a topic (docs/annotate.md)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from .common import _fail, app, force_option


@app.command()
def annotate(run_dir: Path = typer.Argument(..., help="Output folder of 'mmgp train' (holds labels.parquet)."),
             bag: Path = typer.Argument(..., help="The recording the run's log was converted from (.bag, "
                                                  "ROS 2 folder, .db3, .mcap)."),
             out: Path = typer.Option(..., "--out", help="New bag: a .bag file for a ROS 1 bag; for a ROS 2 "
                                                         "bag a .mcap or .db3 file, or a folder (input's storage)."),
             log: Optional[Path] = typer.Option(None, "--log", help="The log the run was trained on (default: "
                                                                    "the one report.json names)."),
             force: bool = force_option()):
    """Copy BAG with the labels of RUN_DIR as topic /mmgp/labels (disturbed, p_disturbed, mode per sample)."""
    from ..convert.annotate import LABEL_TOPIC, LABEL_TYPE, annotate as annotate_bag

    try:
        done = annotate_bag(run_dir, bag, out, log=log, force=force)
    except InputError as exc:
        _fail(exc)
    span = (done.last_ns - done.first_ns) * 1e-9
    typer.echo(f"wrote {done.out}: {done.n_copied} messages copied, {done.n_labels} labels on {LABEL_TOPIC} "
               f"({LABEL_TYPE}) stamped as the samples of {done.topic}, {span:.3f} s")
