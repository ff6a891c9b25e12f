"""`fgjax control` and `fgjax eval` on the tiny shared run: outputs and clear errors."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from fgjax import cli
from fgjax.pipeline.control import parse_vector


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    sys.path.insert(0, str(Path(__file__).parent))
    from _pipeline_run import tiny_run

    return tiny_run(tmp_path_factory.getbasetemp() / "pipeline")


def test_parse_vector():
    np.testing.assert_array_equal(parse_vector("1, -2,3.5"), [1.0, -2.0, 3.5])
    for bad in ("1,2", "a,b,c", "1,2,3,4", "nan,0,0"):
        with pytest.raises(ValueError, match="--vector"):
            parse_vector(bad)


def test_control_renders_and_sweeps(tiny, tmp_path, capsys):
    from fgjax.pipeline import stage2

    run_dir, _ = tiny
    n = stage2.load_stage2(run_dir).s2.num_objects
    if n == 0:
        pytest.skip("no clusters in the tiny run")
    out = tmp_path / "ctl"
    assert cli.main(["control", "--run", str(run_dir), "--object", "1", "--vector", "0.01,0,0", "--out", str(out)]) == 0
    pngs = list(out.glob("object1_*.png"))
    assert len(pngs) == 1
    assert cli.main(["control", "--run", str(run_dir), "--object", "1", "--sweep", "--frames", "2",
                     "--out", str(out)]) == 0
    vids = list(out.glob("object1_sweep.*"))
    assert vids and vids[0].stat().st_size > 0
    capsys.readouterr()
    # errors: object out of range, malformed vector, missing run
    assert cli.main(["control", "--run", str(run_dir), "--object", str(n + 1), "--out", str(out)]) == 2
    assert "out of range" in capsys.readouterr().err
    assert cli.main(["control", "--run", str(run_dir), "--object", "1", "--vector", "1,2", "--out", str(out)]) == 2
    assert "--vector" in capsys.readouterr().err
    assert cli.main(["control", "--run", str(tmp_path / "none"), "--object", "1", "--out", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_eval_writes_metrics(tiny, capsys):
    run_dir, _ = tiny
    assert cli.main(["eval", "--run", str(run_dir)]) == 0
    m = json.loads((run_dir / "metrics.json").read_text())["control"]
    assert -1.0 <= m["ari"] <= 1.0 and -1.0 <= m["ari_controlled"] <= 1.0 and np.isfinite(m["state_psnr"])
    assert len(m["ari_per_view"]) == len(m["ari_controlled_per_view"]) >= 1
    assert m["num_objects_gt"] == 3


def test_render_clusters_writes_id_maps(tiny, tmp_path):
    from fgjax.pipeline import stage2

    run_dir, data = tiny
    out = tmp_path / "ids"
    args = ["render", "--run", str(run_dir), "--cameras", str(data / "transforms_test.json"), "--out", str(out)]
    assert cli.main(args + ["--clusters"]) == 0
    maps = sorted(out.glob("*_ids.npy"))
    assert maps and len(maps) == len(list(out.glob("*_ids.png")))
    n = stage2.load_stage2(run_dir).s2.num_objects
    for path in maps:
        ids = np.load(path)
        assert ids.dtype.kind in "iu" and ids.min() >= 0 and ids.max() <= n
