"""The run engine's promises, for every command that turns images into rows (``reeb
propose``, ``reeb detect``), driven on the command line as a user drives it.

Each test reproduces a fault as a user met it: float options given ``nan``, a killed run's
rows, a ``--kitti-dir`` holding other files, names that change with ``--resume``, a file
name that is not UTF-8 on a picture, an unreadable file named on the command line, a full
disk under each output, an output that is a symbolic link. Small images and a tiny
detector keep it quick.
"""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from reeb_torch.runs.cli import main


# -- float options are finite ------------------------------------------------------------------

@pytest.mark.parametrize("args, option", [
    (["detect", "x.png", "--detector", "d.safetensors", "--min-score", "nan"], "--min-score"),
    (["detect", "x.png", "--detector", "d.safetensors", "--viz-min-score", "-nan"], "--viz-min-score"),
    (["propose", "x.png", "--engine", "ray", "--cpus-per-actor", "nan"], "--cpus-per-actor"),
    (["tune", ".", "--iou", "nan"], "--iou"),
    (["tune", ".", "--timeout", "inf"], "--timeout"),
    (["calibrate", ".", "--box-factor", "nan"], "--box-factor"),
])
def test_a_float_option_that_is_not_finite_is_a_usage_error(args, option):
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2, res.output
    assert option in res.output and "not a finite number" in res.output and "Traceback" not in res.output
