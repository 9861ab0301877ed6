"""3DGS PLY export (engine/export/ply.py): layout, plyfile round trip rendered by the engine,
sequences with their index, and bad-file errors."""
from __future__ import annotations

import json

import numpy as np
import pytest
from export_util import camera, moving_model, render_model
from plyfile import PlyData, PlyElement

from engine.evaluate.metrics import psnr
from engine.export import ply
from engine.export.splats import render_splats, splats_at
from engine.scene.model import view_tensors


@pytest.fixture(scope="module")
def model():
    return moving_model(sh_degree=1)


def test_layout_is_3dgs(tmp_path, model):
    s = splats_at(model, 0.05)
    path = ply.write_ply(tmp_path / "a.ply", s)
    raw = path.read_bytes()
    assert raw.startswith(b"ply\nformat binary_little_endian 1.0\n")
    el = PlyData.read(str(path))["vertex"]
    names = [p.name for p in el.properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(9)]
                     + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert all(el.data.dtype[p] == np.dtype("<f4") for p in names)
    assert len(el.data) == model.gaussians.num_gaussians
    # 3DGS conventions: logit opacity, log scales, wxyz, channel-major f_rest
    np.testing.assert_allclose(1 / (1 + np.exp(-el.data["opacity"])),
                               model.attributes(0.05)["opacities"].detach().numpy(), atol=1e-5)
    np.testing.assert_allclose(el.data["scale_1"], s["log_scales"][:, 1])
    np.testing.assert_allclose(el.data["rot_0"], s["quats"][:, 0])
    np.testing.assert_allclose(el.data["f_rest_3"], s["sh"][:, 1, 1])  # channel G (1), coefficient 1
    np.testing.assert_allclose(el.data["f_rest_2"], s["sh"][:, 3, 0])  # channel R (0), coefficient 3
    np.testing.assert_allclose(0.5 + 0.2820948 * el.data["f_dc_0"],
                               model.attributes(0.05)["colors"].detach().numpy()[:, 0], atol=1e-5)
    assert not list(tmp_path.glob(".*"))  # no temporary left behind


@pytest.mark.parametrize("t", [0.0, 0.13])
def test_reread_renders_like_the_model(tmp_path, model, t):
    view = camera(t)
    want = render_model(model, view)
    back = ply.read_ply(ply.write_ply(tmp_path / "f.ply", splats_at(model, t)))
    got = render_splats(back, view_tensors(view, "cpu"), model.background, model.near_plane)["rgb"]
    assert psnr(got, want) >= 50.0
    # and the check would see a wrong instant: the scene moves between instants
    other = render_splats(ply.read_ply(ply.write_ply(tmp_path / "g.ply", splats_at(model, 0.2 - t))),
                          view_tensors(view, "cpu"), model.background, model.near_plane)["rgb"]
    assert psnr(other, want) < 45.0


def test_sh_degree_zero_round_trip_is_exact(tmp_path):
    m = moving_model(n=50, sh_degree=0, seed=3)
    s = splats_at(m, 0.1)
    back = ply.read_ply(ply.write_ply(tmp_path / "z.ply", s))
    assert back["sh"].shape == (50, 1, 3)
    for k in s:
        np.testing.assert_array_equal(back[k], s[k])


def test_sequence_with_index(tmp_path, model):
    times = np.linspace(0.0, 0.2, 4)
    index_path = ply.write_sequence(tmp_path / "seq", times, lambda t: splats_at(model, t), fps=15.0,
                                    source="unit-test")
    files = sorted(p.name for p in (tmp_path / "seq").iterdir())
    assert files == ["frame_000000.ply", "frame_000001.ply", "frame_000002.ply", "frame_000003.ply", "index.json"]
    index = ply.read_index(tmp_path / "seq")
    assert index == json.loads(index_path.read_text())
    assert [f["time"] for f in index["frames"]] == pytest.approx(times.tolist())
    assert all(f["count"] == model.gaussians.num_gaussians for f in index["frames"])
    assert index["coordinates"]["up_axis"] == "+Z" and index["fps"] == 15.0 and index["num_frames"] == 4
    view = camera(times[2])
    got = render_splats(ply.read_sequence_frame(index_path, 2), view_tensors(view, "cpu"), model.background,
                        model.near_plane)["rgb"]
    assert psnr(got, render_model(model, view)) >= 50.0


def test_missing_property_names_file_and_property(tmp_path, model):
    v = ply.splats_to_vertex_array(splats_at(model, 0.0))
    keep = [n for n in v.dtype.names if n not in ("scale_2", "opacity")]
    arr = np.empty(len(v), dtype=[(n, "<f4") for n in keep])
    for n in keep:
        arr[n] = v[n]
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "bad.ply"))
    with pytest.raises(ply.PlyFormatError, match=r"bad\.ply: missing vertex properties opacity, scale_2"):
        ply.read_ply(tmp_path / "bad.ply")


def test_bad_files(tmp_path, model):
    with pytest.raises(ply.PlyFormatError, match="nothere.ply: PLY file does not exist"):
        ply.read_ply(tmp_path / "nothere.ply")
    good = ply.write_ply(tmp_path / "good.ply", splats_at(model, 0.0)).read_bytes()
    (tmp_path / "torn.ply").write_bytes(good[: len(good) // 2])
    with pytest.raises(ply.PlyFormatError, match="torn.ply: unreadable PLY"):
        ply.read_ply(tmp_path / "torn.ply")
    (tmp_path / "text.ply").write_text("not a ply\n")
    with pytest.raises(ply.PlyFormatError, match="text.ply"):
        ply.read_ply(tmp_path / "text.ply")
    with pytest.raises(ply.PlyFormatError, match="index.json: PLY sequence index does not exist"):
        ply.read_index(tmp_path)
    (tmp_path / "index.json").write_text('{"format": "something-else"}')
    with pytest.raises(ply.PlyFormatError, match="not a bullettime4d-ply-sequence index"):
        ply.read_index(tmp_path)


def test_failed_write_leaves_old_file(tmp_path, model):
    path = ply.write_ply(tmp_path / "keep.ply", splats_at(model, 0.0))
    before = path.read_bytes()
    bad = dict(splats_at(model, 0.0), quats=np.zeros((3, 4), np.float32))  # wrong N
    with pytest.raises(ValueError, match="quats has shape"):
        ply.write_ply(path, bad)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["keep.ply"]


def test_crash_mid_write_leaves_old_file(tmp_path, model, monkeypatch):
    path = ply.write_ply(tmp_path / "keep.ply", splats_at(model, 0.0))
    before = path.read_bytes()

    def torn_write(self, stream):
        stream.write(b"ply\nformat binary_little_endian 1.0\n")
        raise OSError("disk full")

    monkeypatch.setattr(PlyData, "write", torn_write)
    with pytest.raises(OSError, match="disk full"):
        ply.write_ply(path, splats_at(model, 0.1))
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["keep.ply"]


def test_degree_three_has_45_f_rest_and_round_trips(tmp_path):
    rng = np.random.default_rng(5)
    n = 7
    s = {"means": rng.normal(size=(n, 3)), "quats": rng.normal(size=(n, 4)), "log_scales": rng.normal(size=(n, 3)),
         "opacity_logits": rng.normal(size=n), "sh": rng.normal(size=(n, 16, 3))}
    s = {k: v.astype(np.float32) for k, v in s.items()}
    path = ply.write_ply(tmp_path / "d3.ply", s)
    el = PlyData.read(str(path))["vertex"]
    assert sum(p.name.startswith("f_rest_") for p in el.properties) == 45
    # 3DGS: f_rest_{c*15 + j} is coefficient j+1 of channel c
    np.testing.assert_array_equal(el.data["f_rest_29"], s["sh"][:, 15, 1])
    np.testing.assert_array_equal(el.data["f_rest_30"], s["sh"][:, 1, 2])
    back = ply.read_ply(path)
    for k in s:
        np.testing.assert_array_equal(back[k], s[k])
