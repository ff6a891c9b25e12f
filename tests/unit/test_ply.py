"""`fgjax.ply` against an independent reader and writer (`plyfile`): the 3DGS layout's property order, the INRIA
channel-major SH order, every value exactly, and clear errors for files that are not that layout."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from fgjax.gaussians import Gaussians
from fgjax.ply import ply_property_names, read_ply, write_ply


def random_gaussians(n: int, k: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    f = lambda *shape: rng.normal(size=shape).astype(np.float32)
    return Gaussians(f(n, 3), f(n, 3), f(n, 4), f(n), f(n, k, 3))


@pytest.mark.parametrize("k", [1, 4, 9, 16])
def test_write_ply_is_the_3dgs_layout(tmp_path, k):
    """plyfile reads back: binary little-endian, one float32 property per column in the INRIA order, f_rest
    channel-major (all of R's rest coefficients, then G's, then B's), every value bit for bit."""
    g = random_gaussians(37, k)
    path = write_ply(tmp_path / "g.ply", g)
    ply = PlyData.read(str(path))
    assert ply.text is False and ply.byte_order == "<"
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    assert names == ply_property_names(k)
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert len(names) == 17 + 3 * (k - 1)
    assert all(v.data.dtype[n] == np.dtype("<f4") for n in names)
    d = v.data
    col = lambda *ns: np.stack([d[n] for n in ns], -1)
    np.testing.assert_array_equal(col("x", "y", "z"), g.means)
    np.testing.assert_array_equal(col("nx", "ny", "nz"), 0.0)
    np.testing.assert_array_equal(col("f_dc_0", "f_dc_1", "f_dc_2"), g.sh[:, 0])
    for c in range(3):  # channel-major: f_rest_{c (K-1) + j - 1} = sh[:, j, c]
        for j in range(1, k):
            np.testing.assert_array_equal(d[f"f_rest_{c * (k - 1) + j - 1}"], g.sh[:, j, c])
    np.testing.assert_array_equal(d["opacity"], g.opacity_logits)
    np.testing.assert_array_equal(col("scale_0", "scale_1", "scale_2"), g.log_scales)
    np.testing.assert_array_equal(col("rot_0", "rot_1", "rot_2", "rot_3"), g.quats)
    back = read_ply(path)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(back, name), getattr(g, name), err_msg=name)
        assert getattr(back, name).dtype == np.float32


def test_write_ply_keeps_the_rendered_sh_degree_and_writes_atomically(tmp_path):
    g = random_gaussians(5, 16)
    path = write_ply(tmp_path / "g.ply", g, sh_degree=1)
    back = read_ply(path)
    assert back.sh.shape == (5, 4, 3)
    np.testing.assert_array_equal(back.sh, g.sh[:, :4])
    assert [p.name for p in tmp_path.iterdir()] == ["g.ply"]  # no temporary file left
    with pytest.raises(ValueError, match="sh_degree"):
        write_ply(tmp_path / "h.ply", random_gaussians(5, 4), sh_degree=2)
    assert not (tmp_path / "h.ply").exists()
    empty = write_ply(tmp_path / "e.ply", random_gaussians(0, 4))
    assert read_ply(empty).means.shape == (0, 3)


def test_read_ply_reads_a_file_written_by_plyfile(tmp_path):
    """Another writer's file: properties in another order, float64 centres, an extra property, no normals."""
    g = random_gaussians(11, 4, seed=1)
    cols = {"opacity": g.opacity_logits, "extra": np.arange(11, dtype=np.float32)}
    for i in range(3):
        cols[f"scale_{i}"] = g.log_scales[:, i]
        cols[f"f_dc_{i}"] = g.sh[:, 0, i]
    for i in range(4):
        cols[f"rot_{i}"] = g.quats[:, i]
    for c in range(3):
        for j in range(1, 4):
            cols[f"f_rest_{c * 3 + j - 1}"] = g.sh[:, j, c]
    for i, n in enumerate("xyz"):
        cols[n] = g.means[:, i].astype(np.float64)
    arr = np.empty(11, [(n, v.dtype.str) for n, v in cols.items()])
    for n, v in cols.items():
        arr[n] = v
    PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(tmp_path / "o.ply"))
    back = read_ply(tmp_path / "o.ply")
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(back, name), getattr(g, name), err_msg=name)


def test_read_ply_refuses_other_files_by_name(tmp_path):
    g = random_gaussians(3, 4)
    good = write_ply(tmp_path / "g.ply", g).read_bytes()
    cases = {
        "notply": (b"hello\n", "not a PLY file"),
        "ascii": (good.replace(b"binary_little_endian", b"ascii", 1), "only binary_little_endian"),
        "missing": (good.replace(b"property float opacity\n", b""), "missing: opacity"),
        "rest": (good.replace(b"property float f_rest_8\n", b""), "f_rest"),
        "truncated": (good[:-5], "truncated"),
    }
    for name, (data, match) in cases.items():
        (tmp_path / f"{name}.ply").write_bytes(data)
        with pytest.raises(ValueError, match=match) as e:
            read_ply(tmp_path / f"{name}.ply")
        assert f"{name}.ply" in str(e.value)
