"""``fgjax bench track`` on the tiny synthetic run: both modes run, draw what they say and agree."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from fgjax.bench import track


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from _pipeline_run import shared_base, tiny_run

    return tiny_run(shared_base(tmp_path_factory) / "pipeline")


def test_bench_track_times_both_modes_and_their_poses_agree(tiny, capsys):
    run_dir, data = tiny
    args = ["--run", str(run_dir), "--data", str(data), "--start", "1", "--frames", "2", "--steps", "3",
            "--repeats", "1"]
    assert track.main(args) == 0
    out = capsys.readouterr().out
    m = re.search(r"all ([\d.]+), subset ([\d.]+) \(ratio ([\d.]+)\); Gaussians drawn per step: all (\d+), "
                  r"subset (\d+) of (\d+); largest pose difference ([\d.e+-]+)", out)
    assert m, out
    assert float(m.group(1)) > 0 and float(m.group(2)) > 0
    assert int(m.group(5)) <= int(m.group(4)) <= int(m.group(6))
    assert float(m.group(7)) < 1e-4
    # bad input: a clear message naming the option, exit status 2
    assert track.main(["--run", str(run_dir), "--data", str(data), "--start", "7", "--frames", "3"]) == 2
    assert "--start 7 --frames 3" in capsys.readouterr().err
    assert track.main(["--run", str(run_dir), "--data", str(data), "--start", "1", "--frames", "3",
                       "--objects", "9"]) == 2
    assert "--objects [9]" in capsys.readouterr().err
