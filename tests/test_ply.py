"""Gaussians as PLY in the standard 3DGS layout (docs/spec/training.md TRN-10), checked against
the layout itself (property order, channel-major f_rest, raw logits/log-scales/wxyz), not only by
a round trip."""
from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

import refgs
from refgs.errors import SceneError
from refgs.io import read_gaussians_ply, write_gaussians_ply
from refgs.io.ply import gaussian_ply_properties


def gaussians(n=3, k=16, seed=0):
    rng = np.random.default_rng(seed)
    return refgs.Gaussians(rng.standard_normal((n, 3)), rng.standard_normal((n, 3)),
                           rng.standard_normal((n, 4)) * 3, rng.standard_normal(n),
                           rng.standard_normal((n, k, 3)))


def test_property_order_is_the_3dgs_layout(tmp_path):
    write_gaussians_ply(tmp_path / "g.ply", gaussians())
    ply = PlyData.read(str(tmp_path / "g.ply"))
    names = [p.name for p in ply["vertex"].properties]
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert names == expected == gaussian_ply_properties(16)
    assert all(p.val_dtype in ("f4", "float32") for p in ply["vertex"].properties)
    assert ply.text is False and ply.byte_order == "<"
    assert len(names) == 62  # 3 + 3 + 48 + 1 + 3 + 4, the size of a degree-3 3DGS PLY


def test_values_land_in_the_right_properties(tmp_path):
    n, k = 2, 16
    sh = np.zeros((n, k, 3))
    for c in range(3):
        for j in range(k):
            sh[:, j, c] = 100 * c + j + 0.5          # encodes (channel, coefficient)
    g = refgs.Gaussians([[1, 2, 3], [4, 5, 6]], np.log([[0.5, 0.25, 2.0]] * 2),
                        [[0.5, -1.0, 2.0, 0.25]] * 2, [-2.0, 3.0], sh)
    write_gaussians_ply(tmp_path / "g.ply", g)
    v = PlyData.read(str(tmp_path / "g.ply"))["vertex"]
    assert v["x"].tolist() == [1, 4] and v["z"].tolist() == [3, 6]
    assert v["nx"].tolist() == [0, 0] and v["nz"].tolist() == [0, 0]
    for c in range(3):
        assert v[f"f_dc_{c}"][0] == 100 * c + 0.5
        for j in range(1, k):
            # channel-major: f_rest index = c * (K - 1) + (j - 1)
            assert v[f"f_rest_{c * (k - 1) + (j - 1)}"][0] == 100 * c + j + 0.5
    assert v["f_rest_0"][0] == 1.5 and v["f_rest_15"][0] == 101.5 and v["f_rest_44"][0] == 215.5
    assert v["opacity"].tolist() == [-2.0, 3.0]                       # logit, not sigmoid
    np.testing.assert_allclose(v["scale_2"], np.log(2.0), rtol=1e-7)  # log, not exp
    assert [v[f"rot_{i}"][0] for i in range(4)] == [0.5, -1.0, 2.0, 0.25]  # w x y z, unnormalised


def test_reads_a_file_written_in_the_original_way(tmp_path):
    """A file built the way 3DGS save_ply builds it: features_rest (N, K-1, 3) transposed to
    (N, 3, K-1) and flattened."""
    g = gaussians(n=4, k=9, seed=1)
    n, k = 4, 9
    rest = np.transpose(g.sh[:, 1:, :], (0, 2, 1)).reshape(n, -1)
    cols = np.concatenate([g.means, np.zeros((n, 3)), g.sh[:, 0, :], rest,
                           g.opacity_logits[:, None], g.log_scales, g.quats], axis=1)
    names = gaussian_ply_properties(k)
    rows = np.empty(n, dtype=[(nm, "f4") for nm in names])
    for i, nm in enumerate(names):
        rows[nm] = cols[:, i]
    PlyData([PlyElement.describe(rows, "vertex")]).write(str(tmp_path / "orig.ply"))
    back = read_gaussians_ply(tmp_path / "orig.ply")
    for f in refgs.Gaussians.FIELDS:
        np.testing.assert_array_equal(getattr(back, f), getattr(g, f).astype(np.float32))


@pytest.mark.parametrize("k", [1, 4, 16])
def test_round_trip(tmp_path, k):
    g = gaussians(n=5, k=k)
    write_gaussians_ply(tmp_path / "a.ply", g, float_type="f8")
    back = read_gaussians_ply(tmp_path / "a.ply")
    for f in refgs.Gaussians.FIELDS:
        assert np.array_equal(getattr(back, f), getattr(g, f))
    write_gaussians_ply(tmp_path / "b.ply", g)
    back32 = read_gaussians_ply(tmp_path / "b.ply", dtype=np.float32)
    assert back32.dtype == np.float32
    np.testing.assert_array_equal(back32.sh, g.sh.astype(np.float32))


def test_empty_model(tmp_path):
    write_gaussians_ply(tmp_path / "e.ply", refgs.Gaussians.empty(16))
    assert len(read_gaussians_ply(tmp_path / "e.ply")) == 0


def test_bad_files_name_the_file(tmp_path):
    path = tmp_path / "g.ply"
    write_gaussians_ply(path, gaussians())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 50])
    with pytest.raises(SceneError, match=str(path)):
        read_gaussians_ply(path)
    with pytest.raises(SceneError, match="not found"):
        read_gaussians_ply(tmp_path / "none.ply")
    rows = np.zeros(2, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(rows, "vertex")]).write(str(tmp_path / "xyz.ply"))
    with pytest.raises(SceneError, match="3DGS Gaussian layout"):
        read_gaussians_ply(tmp_path / "xyz.ply")
    (tmp_path / "junk.ply").write_bytes(b"hello world")
    with pytest.raises(SceneError, match="junk.ply"):
        read_gaussians_ply(tmp_path / "junk.ply")


def test_inconsistent_shapes_refused(tmp_path):
    bad = refgs.Gaussians(np.zeros((2, 3)), np.zeros((1, 3)), np.zeros((2, 4)), np.zeros(2),
                          np.zeros((2, 1, 3)))
    with pytest.raises(ValueError, match="log_scales"):
        write_gaussians_ply(tmp_path / "g.ply", bad)
    assert list(tmp_path.iterdir()) == []


def test_write_is_atomic(tmp_path, monkeypatch):
    """A write that dies half-way leaves the previous file untouched and no temporary file."""
    path = tmp_path / "g.ply"
    write_gaussians_ply(path, gaussians())
    before = path.read_bytes()

    def dying_write(self, stream):
        stream.write(b"ply\nformat binary_little_endian 1.0\n")
        raise KeyboardInterrupt

    monkeypatch.setattr(PlyData, "write", dying_write)
    with pytest.raises(KeyboardInterrupt):
        write_gaussians_ply(path, gaussians(seed=5))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.ply"]
