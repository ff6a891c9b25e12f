"""`fgjax export` and `fgjax view` on the tiny shared run: the .ply file read back by an independent reader renders as
the run does; the viewer's Gaussians render as `fgjax control` does and move one object alone; the served page
carries the splat and one slider per object, answers a slider, and stops cleanly on Ctrl-C.

The tiny run's one object never moved in its 8 training steps (a zero trajectory, an untrained control network),
so the tests that move objects use a copy of it with a made-up stage 2 (`moving_run`): that object split in two,
each given a straight trajectory, and a control network whose output layer is random (scaled so that an object at
the end of its trajectory moves by about a tenth of a scene unit), so that a vector moves its object's Gaussians."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import equinox as eqx
import imageio.v3 as iio
import jax.numpy as jnp
import numpy as np
import pytest
from _browser import Browser, ViserClient, chromium, splat_centers
from _pipeline_run import shared_base, tiny_run
from plyfile import PlyData
from scipy.spatial.transform import Rotation

import fgjax
from fgjax import cli
from fgjax.apps import view
from fgjax.data.cameras import read_cameras
from fgjax.data.scene import Normalization
from fgjax.gaussians import SH_C0, Gaussians, activate
from fgjax.method import result as stage2
from fgjax.method.splats import (
    active_slots,
    object_labels,
    scene_gaussians,
    trajectory_vectors,
    viewer_gaussians,
)
from fgjax.ply import ply_property_names, read_ply

REPO = Path(__file__).resolve().parents[2]

FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return tiny_run(shared_base(tmp_path_factory) / "pipeline")


@pytest.fixture(scope="module")
def moving_run(tiny, tmp_path_factory) -> Path:
    """A copy of the tiny run whose stage 2 has two objects that move (module docstring)."""
    run_dir = tmp_path_factory.mktemp("moving") / "run"
    shutil.copytree(tiny[0], run_dir)
    run = stage2.load_stage2(run_dir)
    s2 = run.s2
    labels = s2.labels.copy()
    x = np.asarray(run.state.params["gaussians"].means)[:, 0]
    first = labels == 0
    assert first.sum() >= 10, "the tiny run's object is too small to split"
    labels[first & (x > np.median(x[first]))] = 1
    ramp = np.linspace(0.0, 1.0, len(s2.traj_times))[:, None]
    start = s2.traj[0, :1]
    traj = np.stack([start + ramp * [0.3, 0.0, 0.0], start + ramp * [0.0, 0.0, 0.3]])
    rng = np.random.default_rng(0)
    control = eqx.tree_at(lambda c: (c.weights[-1], c.biases[-1]), s2.control,
                          (jnp.asarray(rng.normal(size=s2.control.weights[-1].shape) * 3e-4, jnp.float32),
                           jnp.asarray(rng.normal(size=s2.control.biases[-1].shape) * 3e-4, jnp.float32)))
    stage2.save_stage2(run_dir, stage2.Stage2Result(labels, s2.dynamic, s2.scores, traj, s2.traj_times, control,
                                                    s2.meta, s2.refit))
    return run_dir


def first_camera(run: stage2.LoadedRun, data: Path):
    """(viewmat, K, w, h) of the first training camera."""
    _, vm, K, _, w, h = read_cameras(data / "transforms_train.json", Normalization.from_dict(run.meta["normalization"]),
                                     run.meta["width"], run.meta["height"])[0]
    return vm, K, w, h


def render(run: stage2.LoadedRun, g: Gaussians, vm, K, w, h) -> np.ndarray:
    """[H, W, 3] of Gaussians read back, drawn directly with `fgjax.rasterization` (SH colours up to the run's
    degree, the run's background), clipped to [0, 1] as the run's renders are."""
    f32 = lambda a: jnp.asarray(np.asarray(a), jnp.float32)
    g = Gaussians(*(f32(getattr(g, f)) for f in FIELDS))
    vm, K = f32(vm), f32(K)
    q, s, o = activate(g)
    campos = -(vm[:3, :3].T @ vm[:3, 3])
    colors = jnp.maximum(fgjax.spherical_harmonics(run.cfg.model.sh_degree, g.means - campos, g.sh) + 0.5, 0.0)
    img, _, _ = fgjax.rasterization(g.means, q, s, o, colors, vm, K, int(w), int(h),
                                    background=f32(run.cfg.model.background), tile_size=run.cfg.train.tile_size)
    return np.clip(np.asarray(img), 0.0, 1.0)


def assert_same_gaussians(a: Gaussians, b: Gaussians) -> None:
    for f in FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)), err_msg=f)


# ---------------------------------------------------------------------------------------------- export


def test_export_at_a_time_reads_back_exactly_and_renders_as_the_run(tiny, tmp_path, capsys):
    """The stage-1 scene at t = 0.5: plyfile reads every field of every active Gaussian exactly, and the Gaussians
    read back render as the run renders itself (max abs error < 1e-5)."""
    run_dir, data = tiny
    out = tmp_path / "sub" / "scene.ply"
    capsys.readouterr()
    assert cli.main(["export", "--run", str(run_dir), "--out", str(out), "--time", "0.5"]) == 0
    assert "stage-1 scene at time 0.5" in capsys.readouterr().out
    run = stage2.load_stage2(run_dir)
    want = scene_gaussians(run, time=0.5)
    k = (run.cfg.model.sh_degree + 1) ** 2
    v = PlyData.read(str(out))["vertex"]
    assert [p.name for p in v.properties] == ply_property_names(k)
    assert len(v.data) == len(active_slots(run)) == int(np.sum(np.asarray(run.state.densify.alive)))
    d = v.data
    col = lambda *ns: np.stack([d[n] for n in ns], -1)
    np.testing.assert_array_equal(col("x", "y", "z"), want.means)
    np.testing.assert_array_equal(col("scale_0", "scale_1", "scale_2"), want.log_scales)
    np.testing.assert_array_equal(col("rot_0", "rot_1", "rot_2", "rot_3"), want.quats)
    np.testing.assert_array_equal(d["opacity"], want.opacity_logits)
    np.testing.assert_array_equal(col("f_dc_0", "f_dc_1", "f_dc_2"), want.sh[:, 0])
    rest = col(*(f"f_rest_{i}" for i in range(3 * (k - 1)))).reshape(-1, 3, k - 1)
    np.testing.assert_array_equal(rest, np.transpose(want.sh[:, 1:k], (0, 2, 1)))
    got = read_ply(out)
    assert_same_gaussians(got, Gaussians(*(getattr(want, f) if f != "sh" else want.sh[:, :k] for f in FIELDS)))
    vm, K, w, h = first_camera(run, data)
    img, _, _ = run.render_geometry(*run.deformed(0.5), vm, K, w, h)
    err = np.abs(render(run, got, vm, K, w, h) - np.clip(np.asarray(img), 0.0, 1.0)).max()
    assert err < 1e-5, err


def test_export_with_controls_snaps_and_renders_as_fgjax_control(moving_run, tiny, tmp_path, capsys):
    """Objects 1 and 2 moved by vectors far off their trajectories: both snapped (and said so), and the file
    renders as `render_controlled` draws the snapped vectors (max abs error < 1e-5)."""
    out = tmp_path / "moved.ply"
    capsys.readouterr()
    assert cli.main(["export", "--run", str(moving_run), "--out", str(out), "--object", "1", "--vector", "5,0,0",
                     "--object", "2", "--vector=0,-5,0.1"]) == 0
    said = capsys.readouterr().out
    assert "object 1: vector [5.0, 0.0, 0.0] snapped to [0.3, 0.0, 0.0]" in said
    assert "object 2: vector [0.0, -5.0, 0.1] snapped to [0.0, 0.0, 0.1]" in said and "controlled scene" in said
    assert cli.main(["export", "--run", str(moving_run), "--out", str(tmp_path / "on.ply"), "--object", "2",
                     "--vector", "0,0,0.15"]) == 0
    assert "object 2: vector [0.0, 0.0, 0.15] lies on its trajectory (time 0.5000)" in capsys.readouterr().out
    run = stage2.load_stage2(moving_run)
    vectors = np.array([stage2.snap_vector(run.s2, 0, [5, 0, 0])[0], stage2.snap_vector(run.s2, 1, [0, -5, 0.1])[0]])
    got = read_ply(out)
    assert_same_gaussians(got, scene_gaussians(run, vectors=vectors))
    vm, K, w, h = first_camera(run, tiny[1])
    want = stage2.render_controlled(run, vectors, vm, K, w, h)
    err = np.abs(render(run, got, vm, K, w, h) - want).max()
    assert err < 1e-5, err
    rest = stage2.render_controlled(run, np.zeros_like(vectors), vm, K, w, h)
    assert np.abs(want - rest).max() > 1e-3  # the objects did move on screen


@pytest.mark.parametrize("args,needle", [
    (["--object", "1"], "one --vector per --object"),
    (["--object", "1", "--vector", "0,0,0", "--time", "0.5"], "not both"),
    (["--object", "3", "--vector", "0,0,0"], "out of range"),
    (["--object", "1", "--vector", "1,2"], "--vector"),
    (["--time", "2"], "--time must lie in [0, 1]"),
])
def test_export_refuses_bad_options_in_one_line(moving_run, tmp_path, capsys, args, needle):
    capsys.readouterr()
    assert cli.main(["export", "--run", str(moving_run), "--out", str(tmp_path / "x.ply"), *args]) == 2
    err = capsys.readouterr().err
    assert needle in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert not (tmp_path / "x.ply").exists()


def test_export_controls_on_a_run_without_stage2_say_what_to_run(tiny, tmp_path, capsys):
    bare = tmp_path / "bare"
    shutil.copytree(tiny[0], bare, ignore=shutil.ignore_patterns(stage2.STAGE2_NAME))
    capsys.readouterr()
    assert cli.main(["export", "--run", str(bare), "--out", str(tmp_path / "x.ply"), "--object", "1", "--vector",
                     "0,0,0"]) == 2
    assert "fgjax stage2" in capsys.readouterr().err
    assert cli.main(["export", "--run", str(bare), "--out", str(tmp_path / "s.ply")]) == 0  # stage 1 needs no stage 2
    assert read_ply(tmp_path / "s.ply").capacity == len(active_slots(stage2.load_stage2(bare, require_stage2=False)))


# ---------------------------------------------------------------------------------------------- the viewer's scene


def test_viewer_gaussians_render_as_fgjax_control(moving_run, tiny):
    """`viewer_gaussians` at trajectory positions: its Gaussians render as `render_controlled` with the same
    (already snapped) vectors; its activated arrays are the raw ones' covariance (scipy's rotation), DC colour
    and opacity; with no controls, the stage-1 scene at the time renders as the run's own render."""
    run = stage2.load_stage2(moving_run)
    vm, K, w, h = first_camera(run, tiny[1])
    positions = np.array([0.7, 0.25])
    vectors = trajectory_vectors(run.s2, positions)
    np.testing.assert_allclose(vectors, [[0.21, 0.0, 0.0], [0.0, 0.0, 0.075]], atol=1e-12)
    for k in range(2):  # points of the trajectory snap to themselves
        np.testing.assert_allclose(stage2.snap_vector(run.s2, k, vectors[k])[0], vectors[k], atol=1e-12)
    s = viewer_gaussians(run, 0.9, positions)  # the time is unused with controls
    err = np.abs(render(run, s.gaussians, vm, K, w, h) - stage2.render_controlled(run, vectors, vm, K, w, h)).max()
    assert err < 1e-5, err
    g = s.gaussians
    rot = Rotation.from_quat(np.asarray(g.quats, np.float64)[:, [1, 2, 3, 0]]).as_matrix()
    var = np.exp(2.0 * np.asarray(g.log_scales, np.float64))
    cov = np.einsum("nij,nj,nkj->nik", rot, var, rot)
    np.testing.assert_allclose(s.covariances, cov, rtol=1e-4, atol=1e-6 * cov.max())  # float32 round-off
    np.testing.assert_allclose(s.rgbs, np.clip(SH_C0 * g.sh[:, 0] + 0.5, 0.0, 1.0), atol=1e-6)
    np.testing.assert_allclose(s.opacities[:, 0], 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64))),
                               atol=1e-6)
    np.testing.assert_array_equal(s.centers, g.means)
    np.testing.assert_array_equal(s.labels, run.s2.labels[active_slots(run)])
    s1 = viewer_gaussians(run, 0.25, None)
    img, _, _ = run.render_geometry(*run.deformed(0.25), vm, K, w, h)
    err = np.abs(render(run, s1.gaussians, vm, K, w, h) - np.clip(np.asarray(img), 0.0, 1.0)).max()
    assert err < 1e-5, err


def test_moving_one_control_moves_only_its_object(moving_run):
    """Object 1 at the end of its trajectory: its Gaussians move, the static ones stay exactly where they were, and
    object 2's stay to round-off (each object's rigid fit of an unmoved object is the identity to float32
    round-off); and the other way round."""
    run = stage2.load_stage2(moving_run)
    labels = object_labels(run)
    rest = viewer_gaussians(run, None, [0.0, 0.0])
    for k in range(2):
        pos = np.zeros(2)
        pos[k] = 1.0
        moved = viewer_gaussians(run, None, pos)
        d = np.linalg.norm(moved.centers - rest.centers, axis=1)
        assert d[labels == k].max() > 1e-3, d[labels == k].max()
        np.testing.assert_array_equal(moved.gaussians.means[labels == -1], rest.gaussians.means[labels == -1])
        assert d[labels == 1 - k].max() < 1e-6, d[labels == 1 - k].max()
        np.testing.assert_array_equal(moved.rgbs, rest.rgbs)
    with pytest.raises(ValueError, match=r"positions must lie in \[0, 1\]"):
        viewer_gaussians(run, None, [1.5, 0.0])
    with pytest.raises(ValueError, match="one per object"):
        viewer_gaussians(run, None, [0.5])


def test_viewer_on_a_run_without_stage2_shows_stage1(tiny, tmp_path):
    bare = tmp_path / "bare"
    shutil.copytree(tiny[0], bare, ignore=shutil.ignore_patterns(stage2.STAGE2_NAME))
    run, note = view.load_viewed_run(str(bare))
    assert run.s2 is None and "controls need `fgjax stage2 --run" in note
    s = view.compute(run, {"mode": view.CONTROLLED, "time": 0.5, "positions": np.zeros(0), "by_id": True})
    assert_same_gaussians(s.gaussians, scene_gaussians(run, time=0.5))
    assert np.all(s.labels == -1)
    with pytest.raises(stage2.Stage2Error, match="fgjax stage2"):
        viewer_gaussians(run, None, [0.5])


# ---------------------------------------------------------------------------------------------- the server


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Served:
    """`fgjax view` in a subprocess; its output collected by a thread."""

    def __init__(self, run_dir: Path):
        self.port = free_port()
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
        self.proc = subprocess.Popen([sys.executable, "-m", "fgjax.cli", "view", "--run", str(run_dir), "--port",
                                      str(self.port)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     env=env)
        self.lines: list[str] = []
        self.reader = threading.Thread(target=lambda: self.lines.extend(self.proc.stdout), daemon=True)
        self.reader.start()
        self.url = f"http://127.0.0.1:{self.port}"
        end = time.time() + 180
        while not any(self.url in ln and "fgjax view" in ln for ln in self.lines):
            if self.proc.poll() is not None or time.time() > end:
                self.kill()
                raise AssertionError(f"fgjax view did not start: {''.join(self.lines)}")
            time.sleep(0.1)

    def stop(self) -> int:
        """SIGINT (Ctrl-C); the exit status."""
        self.proc.send_signal(signal.SIGINT)
        code = self.proc.wait(timeout=60)
        self.close()
        return code

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.close()

    def close(self) -> None:
        self.reader.join(timeout=10)
        self.proc.stdout.close()


def test_view_serves_the_splat_and_a_slider_per_object_and_stops_on_ctrl_c(moving_run):
    """A client gets the splat (every active Gaussian, at the controlled scene's rest state), a time slider, one
    slider per object, the colour toggle and a frustum per training camera; moving object 1's slider sends new
    centres that move object 1 alone, as `viewer_gaussians` computes them; SIGINT stops the server with status 0."""
    run = stage2.load_stage2(moving_run)
    labels = object_labels(run)
    served = Served(moving_run)
    try:
        client = ViserClient(f"ws://127.0.0.1:{served.port}")
        labels_of = lambda ms: {m.get("props", {}).get("label") for m, _ in ms}
        client.receive(lambda ms: {"object 2", "colour by object"} <= labels_of(ms)
                       and any(m["type"] == "GaussianSplatsMessage" for m, _ in ms), timeout=60)
        (splat, bufs), = client.of_type("GaussianSplatsMessage")
        centers = splat_centers(bufs[splat["props"]["buffer"]["__binary_index"]])
        rest = viewer_gaussians(run, None, [0.0, 0.0])
        assert centers.shape == (len(active_slots(run)), 3)
        np.testing.assert_allclose(centers, rest.centers, atol=1e-6)
        sliders = [m["props"]["label"] for m, _ in client.of_type("GuiSliderMessage")]
        assert sliders == ["time", "object 1", "object 2"]
        assert "colour by object" in labels_of(client.of_type("GuiCheckboxMessage"))
        assert len(client.of_type("CameraFrustumMessage")) == 8  # the tiny scene's training cameras
        client.set_value("object 1", 1.0)
        update = lambda ms: [(m, b) for m, b in ms if m["type"] == "SceneNodeUpdateMessage" and m["name"] == "/splat"
                             and "buffer" in m["updates"]]
        client.receive(lambda ms: update(ms), timeout=60)
        m, b = update(client.messages)[-1]
        moved = splat_centers(b[m["updates"]["buffer"]["__binary_index"]])
        np.testing.assert_allclose(moved, viewer_gaussians(run, None, [1.0, 0.0]).centers, atol=1e-5)
        d = np.linalg.norm(moved - centers, axis=1)
        assert d[labels == 0].max() > 1e-3 and d[labels != 0].max() < 1e-5
        client.close()
        assert served.stop() == 0
        out = "".join(served.lines)
        assert "fgjax view: stopped" in out and "Traceback" not in out, out
    finally:
        served.kill()


def test_view_on_a_busy_port_is_one_line_and_exit_2(tiny, capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        capsys.readouterr()
        assert cli.main(["view", "--run", str(tiny[0]), "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"port {port} on 127.0.0.1 is busy" in err and "--port" in err and len(err.strip().splitlines()) == 1, err


def test_view_without_viser_says_how_to_install_it(tiny, capsys, monkeypatch):
    monkeypatch.setattr(view, "viser", None)
    capsys.readouterr()
    assert cli.main(["view", "--run", str(tiny[0])]) == 2
    err = capsys.readouterr().err
    assert "pip install 'fgjax[viewer]'" in err and len(err.strip().splitlines()) == 1, err


def test_view_page_draws_the_splat_in_a_browser(moving_run, tmp_path):
    """A headless Chromium loads the page; a screenshot after the splat arrives is not blank: left of the GUI panel,
    below the browser's notice, over a tenth of the pixels differ from the most common colour (the background)."""
    exe = chromium()
    if exe is None:
        pytest.skip("no Chromium for the screenshot test: install one (apt-get install chromium)")
    served = Served(moving_run)
    browser = None
    try:
        browser = Browser(exe, 800, 600)
        browser.open(served.url)
        end, share = time.time() + 90, 0.0
        while time.time() < end and share <= 0.1:
            time.sleep(1.0)
            img = browser.screenshot()
            h, w = img.shape[:2]
            part = img[int(0.35 * h):, : int(0.6 * w)].reshape(-1, 3).astype(np.int64)
            colours, counts = np.unique(part, axis=0, return_counts=True)
            background = colours[np.argmax(counts)]
            share = float(np.mean(np.abs(part - background).sum(-1) > 30))
        iio.imwrite(tmp_path / "view.png", img)
        assert share > 0.1, f"the page looks blank ({share:.3f} of the pixels drawn; {tmp_path / 'view.png'})"
    finally:
        if browser is not None:
            browser.close()
        assert served.stop() == 0
        served.kill()


def test_an_exported_ply_opens_in_viser(tiny, tmp_path):
    """The .ply read back by an independent reader (plyfile) becomes a viser splat: its activated Gaussians
    (`splat_arrays`, the viewer's own formulas) go into `scene.add_gaussian_splats` of a running viser server, one
    per vertex, finite, with positive-definite covariances."""
    import viser

    from fgjax.method.splats import splat_arrays

    run_dir, _ = tiny
    out = tmp_path / "scene.ply"
    assert cli.main(["export", "--run", str(run_dir), "--out", str(out), "--time", "0.25"]) == 0
    d = PlyData.read(str(out))["vertex"].data
    col = lambda *ns: np.stack([np.asarray(d[n], np.float32) for n in ns], -1)
    k = sum(1 for n in d.dtype.names if n.startswith("f_rest_")) // 3 + 1
    sh = np.concatenate([col("f_dc_0", "f_dc_1", "f_dc_2")[:, None],
                         np.transpose(col(*(f"f_rest_{i}" for i in range(3 * (k - 1)))).reshape(-1, 3, k - 1),
                                      (0, 2, 1))], 1)
    g = Gaussians(means=col("x", "y", "z"), log_scales=col("scale_0", "scale_1", "scale_2"),
                  quats=col("rot_0", "rot_1", "rot_2", "rot_3"), opacity_logits=np.asarray(d["opacity"], np.float32),
                  sh=sh)
    cov, rgb, opa = (np.asarray(x) for x in splat_arrays(g))
    assert np.all(np.isfinite(cov)) and np.all(np.linalg.eigvalsh(cov.astype(np.float64)) > 0)
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        handle = server.scene.add_gaussian_splats("/ply", np.asarray(g.means), cov, rgb, opa)
        assert handle is not None and len(g.means) == len(d) > 0
    finally:
        server.stop()
