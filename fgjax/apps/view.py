"""``fgjax view``: an interactive web viewer of a run, on viser (the optional extra ``fgjax[viewer]``).

    fgjax view --run RUN [--port 8080] [--host 127.0.0.1]

Serves a page (open the printed URL in a browser) with the run's splat, the training cameras as frustums, and a
panel: the scene (the stage-1 scene at a time, or the controlled scene), a time slider for the stage-1 scene, one
slider per discovered object (its position along its trajectory, 0 the rest state, snapped as ``fgjax control``
snaps a vector; the other objects stay where their sliders are), a toggle that colours the Gaussians by object id,
and one that shows or hides the cameras. A change recomputes only the Gaussians on the server
(`fgjax.method.splats.viewer_gaussians`), never an image: the browser draws the splat. Splat colours are the
SH's DC term (the viewer has no view-dependent colour).

A run without stage-2 results shows the stage-1 scene (controls need ``fgjax stage2``). Runs until Ctrl-C.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import math
import signal
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np

from fgjax.data.cameras import read_cameras
from fgjax.data.scene import Normalization
from fgjax.geometry import rotmat_to_quat, viewmat_to_c2w
from fgjax.method import result as stage2
from fgjax.method.splats import Splats, viewer_gaussians
from fgjax.method.stage1 import load_run
from fgjax.models.model import refined_viewmats
from fgjax.provenance import read_provenance
from fgjax.viz import ids_to_color

try:
    import viser
except ModuleNotFoundError:  # the optional extra; main() says how to install it
    viser = None

__all__ = ["main", "load_viewed_run", "training_cameras", "frustum_pose", "check_port", "compute"]

STAGE1, CONTROLLED = "stage 1 at a time", "controlled objects"


def training_cameras(run: stage2.LoadedRun) -> list:
    """The run's training cameras [(name, viewmat [4, 4], K [3, 3], time, w, h)] as stage 1 last saw them (refined
    where it refined them), from the data folder the run records; [] when that folder is gone."""
    rec = read_provenance(run.run_dir) or {}
    data = rec.get("data_dir") or (run.s2.meta.get("data_dir") if run.s2 is not None else None)
    tj = Path(data or "") / "transforms_train.json"
    if not data or not tj.is_file():
        return []
    cams = read_cameras(tj, Normalization.from_dict(run.meta["normalization"]), run.meta["width"], run.meta["height"])
    vms = np.stack([c[1] for c in cams])
    if "pose" in run.state.params and len(cams) == run.state.params["pose"].shape[0]:
        vms = refined_viewmats(run.state.params, vms)
    return [(c[0], vm, *c[2:]) for c, vm in zip(cams, vms, strict=True)]


def frustum_pose(viewmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz [4], position [3]) of the camera-to-world transform of an OpenCV world-to-camera 4x4 (viser's frustums
    are OpenCV cameras too: +z forward, +y down)."""
    c2w = viewmat_to_c2w(np.asarray(viewmat, np.float64))
    return np.asarray(rotmat_to_quat(c2w[:3, :3]), np.float64), c2w[:3, 3]


def check_port(host: str, port: int) -> None:
    """OSError with one clear line when ``port`` on ``host`` cannot be listened on (another server holds it).

    viser itself would move to the next free port without a word; the viewer serves the port it was asked for."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        raise OSError(f"--host {host}: {e.strerror}") from None
    for family, kind, proto, _, addr in infos:
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is no conflict
            try:
                s.bind(addr)
                s.listen(1)
            except OSError as e:
                if e.errno == errno.EADDRINUSE:
                    raise OSError(f"port {port} on {host} is busy: another server is listening there; choose a free "
                                  "one with --port") from None
                raise OSError(f"cannot listen on {host} port {port}: {e.strerror}") from None


def load_viewed_run(run_dir: str) -> tuple[stage2.LoadedRun, str | None]:
    """(the run, a note when its stage 2 is missing or unusable: the viewer then shows stage 1 only)."""
    try:
        run = stage2.load_stage2(run_dir, require_stage2=False)
    except stage2.Stage2Error as e:  # stage-2 results that do not fit this stage 1: view stage 1 alone
        cfg, state, spec, meta = load_run(run_dir)
        state.static = meta.get("static", False)
        return stage2.LoadedRun(Path(run_dir), cfg, state, spec, meta, None), f"{e}; showing the stage-1 scene only"
    if run.s2 is None:
        return run, (f"{run_dir} has no stage-2 results: showing the stage-1 scene; controls need "
                     f"`fgjax stage2 --run {run_dir}`")
    if run.s2.num_objects == 0:
        return run, f"{run_dir}: stage 2 found no objects; nothing to control"
    return run, None


class _Viewer:
    """The viewer's state and its scene handles; one worker thread recomputes the Gaussians for the latest state
    (changes that arrive while it computes are merged: the newest wins)."""

    def __init__(self, server, run: stage2.LoadedRun, cameras: list, note: str | None):
        self.server, self.run = server, run
        k = 0 if run.s2 is None else run.s2.num_objects
        self.lock, self.dirty, self.done = threading.Lock(), threading.Event(), threading.Event()
        first = CONTROLLED if k else STAGE1  # objects at rest: a slider then moves its object alone
        self.state = {"mode": first, "time": 0.0, "positions": np.zeros(k), "by_id": False}
        splats = compute(run, self.state)
        self.splat = server.scene.add_gaussian_splats("/splat", splats.centers, splats.covariances,
                                                      splats.rgbs, splats.opacities)
        self._cameras(cameras, splats.centers)
        gui = server.gui
        gui.add_markdown(f"**{run.run_dir.name}**: {len(splats.centers)} Gaussians, {k} object(s)"
                         + (f"\n\n{note}" if note else ""))
        self.mode = gui.add_dropdown("scene", (STAGE1, CONTROLLED) if k else (STAGE1,), initial_value=first)
        self.time = gui.add_slider("time", 0.0, 1.0, 0.01, 0.0, hint="normalised time of the stage-1 scene")
        self.objects = []
        if k:
            with gui.add_folder("objects"):
                for i in range(k):
                    self.objects.append(gui.add_slider(f"object {i + 1}", 0.0, 1.0, 0.01, 0.0,
                                                       hint="position along its trajectory (0: rest, 1: its end)"))
        self.by_id = gui.add_checkbox("colour by object", False, hint="grey: static; one colour per object")
        self.show_cams = gui.add_checkbox("training cameras", bool(cameras))
        self.mode.on_update(lambda _: self._set(mode=self.mode.value))
        self.time.on_update(lambda _: self._set(t=float(self.time.value), mode=STAGE1))
        for i, h in enumerate(self.objects):
            h.on_update(lambda _, i=i, h=h: self._set(position=(i, float(h.value)), mode=CONTROLLED))
        self.by_id.on_update(lambda _: self._set(by_id=bool(self.by_id.value)))
        self.show_cams.on_update(lambda _: self._show_cameras(bool(self.show_cams.value)))
        self.worker = threading.Thread(target=self._loop, name="fgjax-view", daemon=True)
        self.worker.start()

    def _cameras(self, cameras: list, centers: np.ndarray) -> None:
        self.frustums = []
        if not cameras:
            return
        scale = 0.02 * float(self.run.meta.get("scene_extent") or 1.0)
        for name, vm, K, _, w, h in cameras:
            wxyz, pos = frustum_pose(vm)
            self.frustums.append(self.server.scene.add_camera_frustum(
                f"/cameras/{name}", fov=2 * math.atan(h / (2 * K[1, 1])), aspect=w / h, scale=scale, wxyz=wxyz,
                position=pos, color=(60, 120, 220), thickness=1.5, thickness_units="screen"))
        # world up: the mean of the cameras' up (-y); the first camera's view is where a browser starts
        vm = np.stack([c[1] for c in cameras])
        up = -np.mean(vm[:, 1, :3], axis=0)
        up = up / max(np.linalg.norm(up), 1e-12)
        self.server.scene.set_up_direction(tuple(up))
        name, vm0, K0, _, w0, h0 = cameras[0]
        _, pos = frustum_pose(vm0)
        fwd = np.asarray(vm0)[2, :3]
        depth = max(float(np.median((centers - pos) @ fwd)), 1e-3)
        cam = self.server.initial_camera
        cam.position, cam.look_at, cam.up = tuple(pos), tuple(pos + depth * fwd), tuple(-np.asarray(vm0)[1, :3])
        # viser draws a Gaussian only when its centre projects within 1.1x the view, so a view as narrow as the
        # camera's loses the large Gaussians at the image border: the browser starts 1.4x wider
        cam.fov = min(1.4 * 2 * math.atan(h0 / (2 * K0[1, 1])), math.radians(120.0))

    def _show_cameras(self, visible: bool) -> None:
        for f in self.frustums:
            f.visible = visible

    def _set(self, *, mode=None, t=None, position=None, by_id=None) -> None:
        with self.lock:
            if t is not None:
                self.state["time"] = t
            if position is not None:
                self.state["positions"] = self.state["positions"].copy()
                self.state["positions"][position[0]] = position[1]
            if by_id is not None:
                self.state["by_id"] = by_id
            if mode is not None:
                self.state["mode"] = mode
        if mode is not None and self.mode.value != mode:
            self.mode.value = mode  # its callback sets the same mode again
        self.dirty.set()

    def _loop(self) -> None:
        while not self.done.is_set():
            if not self.dirty.wait(0.2):
                continue
            self.dirty.clear()
            with self.lock:
                st = dict(self.state)
            try:
                self.push(compute(self.run, st))
            except Exception as e:  # a failed update keeps the viewer up and says why
                print(f"fgjax view: update failed: {type(e).__name__}: {e}", file=sys.stderr)

    def push(self, splats: Splats) -> None:
        self.splat.set_gaussians(splats.centers, splats.covariances, splats.rgbs, splats.opacities)

    def close(self) -> None:
        self.done.set()
        self.worker.join(timeout=5.0)


def compute(run: stage2.LoadedRun, state: dict) -> Splats:
    """The Gaussians for a viewer state {"mode", "time", "positions" [K], "by_id"}: `viewer_gaussians` of the
    chosen scene, coloured by object id (grey static, `fgjax.viz.ids_to_color`) when "by_id"."""
    controlled = state["mode"] == CONTROLLED and run.s2 is not None and run.s2.num_objects > 0
    s = viewer_gaussians(run, state["time"], state["positions"] if controlled else None)
    if state["by_id"]:
        s = s._replace(rgbs=ids_to_color(s.labels + 1).astype(np.float32) / 255.0)
    return s


def _interrupt(signum, frame):
    raise KeyboardInterrupt


@contextlib.contextmanager
def _stop_on_signals():
    """Ctrl-C (SIGINT) and SIGTERM raise KeyboardInterrupt in the main thread while serving, even where the shell
    started the process with SIGINT ignored (a background job); the previous handlers come back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, _interrupt) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fgjax view", description="Interactive web viewer of a run (viser).")
    p.add_argument("--run", required=True, help="run folder (stage 1; stage 2 for the object controls)")
    p.add_argument("--port", type=int, default=8080, help="port to serve on (default: %(default)s)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default: %(default)s, this machine only; 0.0.0.0: every interface)")
    args = p.parse_args(argv)
    if viser is None:
        raise OSError("fgjax view needs viser, the optional extra: pip install 'fgjax[viewer]'")
    if not 1 <= args.port <= 65535:
        raise ValueError(f"--port must be in 1..65535, got {args.port}")
    if not Path(args.run).is_dir():
        raise FileNotFoundError(f"run folder {args.run} does not exist")
    check_port(args.host, args.port)
    run, note = load_viewed_run(args.run)
    if note:
        print(f"fgjax view: {note}")
    cameras = training_cameras(run)
    with _stop_on_signals():
        server = viser.ViserServer(host=args.host, port=args.port, label="fgjax", verbose=False)
        viewer = None
        try:
            if server.get_port() != args.port:  # taken between the check and the bind
                raise OSError(f"port {args.port} on {args.host} is busy: another server is listening there; choose a "
                              "free one with --port")
            viewer = _Viewer(server, run, cameras, note)
            shown = "localhost" if args.host in ("0.0.0.0", "::") else args.host
            print(f"fgjax view: http://{shown}:{args.port} ({len(cameras)} training cameras; Ctrl-C stops)",
                  flush=True)
            while True:
                time.sleep(0.5)
        except KeyboardInterrupt:
            print("fgjax view: stopped", flush=True)
        finally:
            if viewer is not None:
                viewer.close()
            server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
