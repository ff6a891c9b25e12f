"""Every matrix product of the geometric kernels asks for full float32 precision.

On recent NVIDIA GPUs JAX's default precision multiplies float32 matrices in TF32 (a 10-bit mantissa). On an H200
that put errors of 4e-2 into the rasterizer's colours against the float64 reference (4e-7 at full precision; the
Gaussians binned to tiles changed too: docs/benchmarks.md, "GPU"). A CPU computes in full precision whatever is
asked, so the tests that compare against references cannot see a missing precision here. These tests read the
traced programs instead: under ``jax.default_matmul_precision("default")`` every ``dot_general`` that does not ask
for `fgjax.geometry.HIGHEST` itself is recorded with precision DEFAULT, and the test names it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import look_at

import fgjax
from fgjax import flow, geometry
from fgjax.articulate import phototrack, track
from fgjax.method import camera
from fgjax.models import posed
from fgjax.render.project import project_gaussians

W, H = 32, 24
K = np.array([[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]], np.float32)


def _subjaxprs(value):
    for v in value if isinstance(value, (tuple, list)) else (value,):
        if hasattr(v, "eqns"):
            yield v
        elif hasattr(getattr(v, "jaxpr", None), "eqns"):
            yield v.jaxpr


def _origin(eqn) -> str:
    """file:line of the innermost frame in fgjax (or a dependency) that made the equation."""
    tb = eqn.source_info.traceback
    frames = [f for f in (tb.frames if tb is not None else []) if "/jax/" not in f.file_name]
    return f"{frames[0].file_name}:{frames[0].line_num} ({frames[0].function_name})" if frames else "?"


def _dots(jaxpr):
    """Every dot_general equation in `jaxpr`, those of its sub-programs (scan, cond, jit, custom_vjp) included."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            yield eqn
        for value in eqn.params.values():
            for sub in _subjaxprs(value):
                yield from _dots(sub)


def _low_precision_dots(jaxpr) -> list[str]:
    """Source lines of the dot_general equations in `jaxpr` whose precision is not HIGHEST for both operands."""
    bad = []
    for eqn in _dots(jaxpr):
        prec = eqn.params.get("precision")
        if not (isinstance(prec, tuple) and all(p == jax.lax.Precision.HIGHEST for p in prec)):
            bad.append(f"{_origin(eqn)} precision={prec}")
    return bad


def _check(fn, *args, allow: str | None = None):
    """Traces fn(*args) under the default precision; fails naming every product without HIGHEST (those made in a
    file whose path contains `allow` excepted). Returns the number of products."""
    with jax.default_matmul_precision("default"):
        closed = jax.make_jaxpr(fn)(*args)
    bad = [b for b in _low_precision_dots(closed.jaxpr) if allow is None or allow not in b]
    assert not bad, "matrix products without precision=HIGHEST:\n" + "\n".join(bad)
    return sum(1 for _ in _dots(closed.jaxpr))


def _scene(n=60, seed=0):
    rng = np.random.default_rng(seed)
    f = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return (f(rng.normal(size=(n, 3)) * 0.5), f(rng.normal(size=(n, 4))), f(np.exp(rng.uniform(-3, -2, (n, 3)))),
            f(rng.uniform(0.1, 1.0, n)), f(rng.uniform(0, 1, (n, 3))), f(look_at([0.3, -2.5, 1.0])), f(K))


def test_the_check_sees_a_default_precision_product():
    """The walk finds a plain ``@`` inside jit and scan: the check can fail."""
    def fn(a):
        return jax.lax.scan(lambda c, _: (jax.jit(lambda x: x @ x)(c), None), a, None, length=2)[0]

    with jax.default_matmul_precision("default"):
        closed = jax.make_jaxpr(fn)(jnp.eye(3))
    assert len(_low_precision_dots(closed.jaxpr)) == 1
    assert _check(lambda a: geometry.matmul(a, a), jnp.eye(3)) == 1


def test_rasterizer_forward_and_backward_at_full_precision():
    means, quats, scales, opac, colors, vm, k = _scene()

    def loss(means, quats, scales, opac, colors):
        img, alpha, _ = fgjax.rasterization(means, quats, scales, opac, colors, vm, k, W, H, tile_size=8)
        return jnp.sum(img) + jnp.sum(alpha)

    assert _check(lambda *a: fgjax.rasterization(*a, vm, k, W, H)[:2], means, quats, scales, opac, colors) >= 5
    assert _check(jax.grad(loss, argnums=(0, 1, 2, 3, 4)), means, quats, scales, opac, colors) >= 9
    assert _check(lambda m, q, s, o: project_gaussians(m, q, s, o, vm, k, W, H).means2d, means, quats, scales, opac)


def test_flow_kernels_at_full_precision():
    means, quats, scales, opac, _, vm, k = _scene()
    c2w0 = geometry.se3_inverse(vm)
    c2w1 = geometry.se3_compose(c2w0, geometry.se3_exp(jnp.array([0.01, -0.02, 0.005, 0.03, 0.0, -0.01])))
    _check(flow.camera_velocity, c2w0, c2w1)
    _check(lambda d: flow.reprojection_flow(d, k, c2w0, c2w1), jnp.full((H, W), 2.5, jnp.float32))
    means1 = means + 0.01

    def dyn(m1, aniso):
        out = flow.dynamic_gaussian_flow(means, quats, scales, opac, m1, vm, k, W, H, anisotropic=aniso,
                                         quats1=quats if aniso else None, scales1=scales if aniso else None)
        return jnp.sum(out.flow)

    for aniso in (False, True):
        _check(lambda m1, a=aniso: dyn(m1, a), means1)
        _check(jax.grad(lambda m1, a=aniso: dyn(m1, a)), means1)
    _check(lambda m: flow.composited_inverse_depth(m, quats, scales, opac, vm, k, W, H), means)
    cov = jnp.broadcast_to(jnp.array([[2.0, 0.3], [0.3, 1.5]], jnp.float32), (5, 2, 2))
    _check(flow.gaussian_flow_affine, jnp.zeros((5, 2)), cov, jnp.ones((5, 2)), 1.2 * cov)


def test_geometry_at_full_precision():
    xi = jnp.array([[0.3, -0.2, 0.1, 0.5, 0.0, -0.4]], jnp.float32)
    assert _check(geometry.se3_exp, xi) >= 2
    assert _check(lambda x: geometry.se3_log(geometry.se3_exp(x)), xi) >= 3
    _check(lambda x: geometry.se3_inverse(geometry.se3_exp(x)), xi)
    _check(lambda x: geometry.so3_left_jacobian_inv(x[:, :3]), xi)


@pytest.mark.parametrize("kind", ["revolute", "prismatic"])
def test_joint_fit_and_rigid_increment_at_full_precision(kind):
    """The solvers' own products (optimistix's and lineax's normal equations and Cholesky) included."""
    rng = np.random.default_rng(1)
    j, m = 3, 12
    f = lambda x: jnp.asarray(x, jnp.result_type(float))  # noqa: E731  (the trackers compute in the default float)
    pts = f(rng.normal(size=(j, m, 3)) * 0.2)
    vms = f(np.broadcast_to(look_at([0.2, -2.0, 0.8]), (j, 4, 4)))
    ks = f(np.broadcast_to(K, (j, 3, 3)))
    target = f(rng.uniform(0, W, (j, m, 2)))
    w = f(np.ones((j, m)))
    x0 = f(np.concatenate([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0], np.zeros(j)]))
    centre = f(np.zeros(3))
    assert _check(lambda *a: track._fit_joint_jit(*a, kind=kind, irls=1, huber_px=1.0),
                  x0, pts, target, w, vms, ks, centre) >= 3
    assert _check(lambda p, t: camera.rigid_increment(p, t, w[0], vms[0], ks[0], irls=1), pts[0], target[0]) >= 3


def test_tracking_transforms_at_full_precision():
    x = jnp.array([[0.1, 0.2, -0.1, 0.01, 0.0, 0.02]], jnp.float32)
    _check(lambda x: phototrack.pose_delta(x, jnp.ones((1, 3)), jnp.ones(1)), x)
    means, quats = _scene()[:2]
    poses = geometry.se3_exp(x)
    _check(lambda m, q: posed.transform_gaussians(m, q, jnp.zeros(len(m), jnp.int32), poses), means, quats)


def test_stage1_step_at_full_precision_but_the_fields_mlps():
    """The whole stage-1 step (deformation, pose refinement, rendering, losses, gradients, optimiser): every product
    at HIGHEST except the learned deformation field's MLP (fgjax/models), which may use TF32."""
    from test_stage1 import _cfg, _tiny_scene

    from fgjax.method import stage1
    from fgjax.train.optim import OptimSpec, make_optimizer

    scene = _tiny_scene(True, frames=3)
    state, spec, _ = stage1.initial_state(_cfg(), scene)
    params = dict(state.params, pose=jnp.zeros((3, 6), jnp.float32))
    ospec = OptimSpec(steps=10)
    ss = stage1.StepSpec(spec, 1, scene.width, scene.height, 16384, 8, 0.2, 0.0, 0.05, True)
    step = stage1.make_step(ss, ospec, 4, (0.0, 0.0, 0.0))
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    i = np.array([1])
    args = (params, make_optimizer(ospec, 4).init(params), state.densify, jnp.ones(4, jnp.float32),
            f32(scene.images[i]), f32(scene.viewmats[i]), f32(scene.Ks[i]), f32(scene.times[i]),
            jnp.asarray(i, jnp.int32))
    assert _check(step, *args, allow="/fgjax/models/") >= 10
