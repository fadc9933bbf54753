"""Unreadable inputs (issue 14, class 6): `info`, `preview`, `fit --target` and a scene's [fit] target cache on
files that are truncated, corrupt, of another format, empty, folders, unreadable, USD without an animated
mesh or .npz without its arrays: every one exits 2 with one line naming the file, never a traceback.

Tiny valid caches (a 4 x 4 grid, 3 frames) are written once with the cache writers; each case corrupts a copy.
"""

import os
import pathlib
import pickle
import shutil
import zipfile

import numpy as np
import pytest
from pxr import Usd, UsdGeom

import cloth_warp as cw
import cloth_warp.cache
from cloth_warp.cache import CacheError, CacheReader, NpzCacheWriter, UsdCacheWriter
from cloth_warp.cli import main

FRAMES = 3
POINTS = 25  # a 4 x 4 grid


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """Valid caches by extension: usdc, usda, usd (crate) and npz."""
    d = tmp_path_factory.mktemp("good")
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(4, 4), size=(0.3, 0.3), rotation=cw.quat_from_axis_angle((1, 0, 0), -90.0),
                     position=(0.0, 1.0, 0.0), name="sheet")
    model = b.finalize("cpu")
    q = model.particle_q.numpy()
    paths = {}
    for ext in ("usdc", "usda", "usd", "npz"):
        writer = NpzCacheWriter if ext == "npz" else UsdCacheWriter
        with writer(d / f"good.{ext}", model, fps=30) as w:
            for k in range(FRAMES):
                w.write(q - [0.0, 0.01 * k, 0.0], np.zeros_like(q))
        paths[ext] = d / f"good.{ext}"
    return paths


# -- the corruptions: name -> (extension, maker(good caches, destination path)) ---------------------------------

def _truncated(ext, frac=None, size=None):
    def make(good, dst):
        data = good[ext].read_bytes()
        dst.write_bytes(data[: size if size is not None else int(frac * len(data))])
    return ext, make


def _bytes(ext, data):
    def make(good, dst):
        dst.write_bytes(data)
    return ext, make


def _renamed(src_ext, ext):
    def make(good, dst):
        shutil.copyfile(good[src_ext], dst)
    return ext, make


def _stage(ext, build):
    """A USD stage written with pxr directly (not a cloth_warp cache)."""
    def make(good, dst):
        stage = Usd.Stage.CreateNew(str(dst))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        build(stage)
        stage.GetRootLayer().Save()
    return ext, make


TRI = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)]


def _mesh(stage, path="/World/sheet", points="samples", faces=True, indices=(0, 1, 2), short_frame=False):
    UsdGeom.Xform.Define(stage, "/World")
    mesh = UsdGeom.Mesh.Define(stage, path)
    if points == "samples":
        mesh.GetPointsAttr().Set(TRI, 1)
        mesh.GetPointsAttr().Set(TRI[:2] if short_frame else TRI, 2)
    elif points == "static":
        mesh.GetPointsAttr().Set(TRI)
    if faces:
        mesh.GetFaceVertexCountsAttr().Set([3])
        mesh.GetFaceVertexIndicesAttr().Set(list(indices))


def _npz_edit(edit):
    def make(good, dst):
        with np.load(good["npz"]) as data:
            arrays = {k: data[k] for k in data.files}
        edit(arrays)
        with open(dst, "wb") as fh:
            np.savez(fh, **arrays)
    return "npz", make


def _npy_bytes() -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, np.zeros((FRAMES, POINTS, 3), np.float32))
    return buf.getvalue()


def _npz_flip(good, dst):
    """Bytes flipped inside the compressed positions: the member's CRC fails."""
    data = bytearray(good["npz"].read_bytes())
    with zipfile.ZipFile(good["npz"]) as z:
        info = z.getinfo("positions.npy")
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra) + 8
    for i in range(start, start + 16):
        data[i] ^= 0xFF
    dst.write_bytes(bytes(data))


def _npz_raw_member(good, dst):
    """A zip with the right names whose members are not .npy data."""
    with zipfile.ZipFile(dst, "w") as z:
        for k in ("positions", "triangles", "fps", "start_frame", "metadata"):
            z.writestr(f"{k}.npy", b"not numpy data")


RNG = np.random.default_rng(14)
CASES = {
    # truncated at random offsets (and at the very start, inside the magic bytes)
    **{f"truncated_{ext}_{i}": _truncated(ext, frac=float(f)) for ext in ("usdc", "usda", "usd", "npz")
       for i, f in enumerate(RNG.uniform(0.02, 0.97, 3))},
    **{f"truncated_{ext}_to_{n}_bytes": _truncated(ext, size=n) for ext in ("usdc", "npz") for n in (3, 40)},
    "truncated_usda_to_3_bytes": _truncated("usda", size=3),
    # random bytes under each cache extension
    **{f"random_bytes_{ext}": _bytes(ext, RNG.integers(0, 256, 700, dtype=np.uint8).tobytes())
       for ext in ("usdc", "usda", "usd", "npz")},
    # a zero-byte file
    **{f"empty_{ext}": _bytes(ext, b"") for ext in ("usdc", "usda", "usd", "npz")},
    # text renamed
    **{f"text_as_{ext}": _bytes(ext, b"frame,x,y,z\n1,0.0,1.0,0.0\n2,0.0,0.9,0.0\n") for ext in ("usdc", "usda", "usd", "npz")},
    # other formats under a cache's name
    "usda_as_usdc": _renamed("usda", "usdc"),
    "usdc_as_usda": _renamed("usdc", "usda"),
    "npz_as_usdc": _renamed("npz", "usdc"),
    "npz_as_usd": _renamed("npz", "usd"),
    "usdc_as_npz": _renamed("usdc", "npz"),
    "pickle_as_npz": _bytes("npz", pickle.dumps({"positions": [[0.0, 0.0, 0.0]], "fps": 30.0})),
    "npy_as_npz": ("npz", lambda good, dst: dst.write_bytes(_npy_bytes())),
    "unknown_extension": _renamed("usdc", "abc"),
    # USD without what a cache needs
    "usd_only_xform_usda": _stage("usda", lambda s: UsdGeom.Xform.Define(s, "/World")),
    "usd_only_xform_usdc": _stage("usdc", lambda s: UsdGeom.Xform.Define(s, "/World")),
    "usd_no_prims": _stage("usdc", lambda s: None),
    "usd_mesh_without_faces": _stage("usdc", lambda s: _mesh(s, faces=False)),
    "usd_mesh_without_points": _stage("usda", lambda s: _mesh(s, points=None)),
    "usd_mesh_static_points": _stage("usda", lambda s: _mesh(s, points="static")),
    "usd_mesh_index_out_of_range": _stage("usda", lambda s: _mesh(s, indices=(0, 1, 7))),
    "usd_frame_with_fewer_points": _stage("usdc", lambda s: _mesh(s, short_frame=True)),
    "usd_only_a_collider_mesh": _stage("usda", lambda s: _mesh(s, path="/World/colliders/ball")),
    # .npz without its arrays or with wrong ones
    **{f"npz_without_{k}": _npz_edit(lambda a, k=k: a.pop(k)) for k in ("positions", "fps", "triangles", "start_frame")},
    "npz_empty_zip": ("npz", lambda good, dst: zipfile.ZipFile(dst, "w").close()),
    "npz_positions_pickled_objects": _npz_edit(lambda a: a.update(positions=np.array([object()], dtype=object))),
    "npz_positions_wrong_shape": _npz_edit(lambda a: a.update(positions=np.zeros((FRAMES, POINTS)))),
    "npz_no_frames": _npz_edit(lambda a: a.update(positions=np.zeros((0, POINTS, 3), np.float32))),
    "npz_fps_zero": _npz_edit(lambda a: a.update(fps=np.array(0.0))),
    "npz_fps_not_a_number": _npz_edit(lambda a: a.update(fps=np.array("thirty"))),
    "npz_triangles_out_of_range": _npz_edit(lambda a: a.update(triangles=a["triangles"] + POINTS)),
    "npz_metadata_not_json": _npz_edit(lambda a: a.update(metadata=np.array("{not json"))),
    "npz_member_crc": ("npz", _npz_flip),
    "npz_members_not_numpy": ("npz", _npz_raw_member),
    # not a file one can read
    "directory_usdc": ("usdc", lambda good, dst: dst.mkdir()),
    "directory_npz": ("npz", lambda good, dst: dst.mkdir()),
    "no_read_permission_usdc": _renamed("usdc", "usdc"),
    "no_read_permission_npz": _renamed("npz", "npz"),
    "missing": ("usdc", lambda good, dst: None),
}


def _make(case, good, tmp_path, monkeypatch) -> pathlib.Path:
    ext, maker = CASES[case]
    path = tmp_path / f"{case}.{ext}"
    maker(good, path)
    if case.startswith("no_read_permission"):
        path.chmod(0)
        if os.access(path, os.R_OK):  # root reads anyway: the open the reader does fails as it would for a user
            def denied(file, *args, **kwargs):
                raise PermissionError(13, "Permission denied", str(file))
            monkeypatch.setattr(cloth_warp.cache, "open", denied, raising=False)
    return path


def _scene(tmp_path, target=None) -> pathlib.Path:
    scene = tmp_path / "fit_small.toml"
    table = f'target = {{ cache = "{target.as_posix()}" }}\n' if target is not None else ""
    scene.write_text(f"""
[cloth]
grid = {{ resolution = [4, 4], size = [0.3, 0.3] }}
position = [0.0, 1.0, 0.0]
rotation = {{ axis = [1.0, 0.0, 0.0], angle = -90.0 }}

[[pins]]
select = "corner:top_left"

[fit]
params = ["material.damping"]
iterations = 1
{table}
[output]
frames = {FRAMES - 1}
fps = 30
""")
    return scene


def _argv(command, path, tmp_path):
    if command == "info":
        return ["info", str(path)]
    if command == "preview":
        return ["preview", str(path), "-o", str(tmp_path / "preview.png"), "--size", "16", "16"]
    if command == "fit_target":
        return ["fit", str(_scene(tmp_path)), "--target", str(path), "-q", "-o", str(tmp_path / "fitted.toml")]
    return ["fit", str(_scene(tmp_path, path)), "-q", "-o", str(tmp_path / "fitted.toml")]  # the scene's [fit] target


COMMANDS = ("info", "preview", "fit_target", "fit_scene_target")


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("command", COMMANDS)
def test_unreadable_input_exits_2_naming_the_file(command, case, good, tmp_path, monkeypatch, capfd):
    """Exit 2, one error line on stderr (Python's and USD's own output both: capfd) naming the file, no traceback,
    and nothing written."""
    path = _make(case, good, tmp_path, monkeypatch)
    capfd.readouterr()
    code = main(_argv(command, path, tmp_path))
    out, err = capfd.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, (code, err)
    assert "Traceback" not in err and "Error in '" not in err, err
    assert len(lines) == 1 and lines[0].startswith("cloth-warp: error: ") and path.name in lines[0], err
    assert not (tmp_path / "preview.png").exists() and not (tmp_path / "fitted.toml").exists()


def test_reader_raises_cache_error_naming_the_file(good, tmp_path, monkeypatch):
    """From Python: CacheError (a ValueError) "<path>: <what>" for every case but a missing file."""
    for case in sorted(CASES):
        path = _make(case, good, tmp_path, monkeypatch)
        if case == "missing":
            with pytest.raises(FileNotFoundError):
                CacheReader(path)
            continue
        with pytest.raises(CacheError) as info:
            CacheReader(path)
        assert isinstance(info.value, ValueError) and str(info.value).startswith(f"{path}: "), (case, str(info.value))
        monkeypatch.undo()


@pytest.mark.parametrize("case, expected", [
    ("truncated_usdc_0", "truncated or corrupt binary USD file: its table of contents is at byte"),
    ("truncated_usd_0", "truncated or corrupt binary USD file"),
    ("truncated_usdc_to_40_bytes", "40 bytes, smaller than its 88-byte header"),
    ("truncated_usda_0", "truncated?"),
    ("truncated_npz_0", "truncated or corrupt .npz"),
    ("random_bytes_usdc", "not a binary USD (crate) file"),
    ("empty_npz", "is empty (0 bytes)"),
    ("text_as_usdc", "the file is text"),
    ("usda_as_usdc", "rename it .usda"),
    ("pickle_as_npz", "a Python pickle (pickles are never loaded)"),
    ("usd_only_xform_usda", "holds no cloth mesh"),
    ("usd_mesh_without_faces", "has no faces"),
    ("usd_mesh_static_points", "no time samples"),
    ("usd_frame_with_fewer_points", "2 points at frame 2, 3 at rest"),
    ("npz_without_positions", "no 'positions' array"),
    ("npz_without_fps", "no 'fps' array"),
    ("directory_usdc", "is a directory"),
    ("no_read_permission_usdc", "permission denied"),
])
def test_messages_say_what_is_wrong(case, expected, good, tmp_path, monkeypatch):
    path = _make(case, good, tmp_path, monkeypatch)
    with pytest.raises(CacheError) as info:
        CacheReader(path)
    assert expected in str(info.value), str(info.value)


def test_valid_caches_still_read(good, tmp_path, capfd):
    """The checks refuse nothing the writers write: info and preview of each format, the reader's frames."""
    for ext, path in good.items():
        reader = CacheReader(path)
        assert (reader.frame_count, len(reader.meshes[0]["points"])) == (FRAMES, POINTS)
        np.testing.assert_allclose(reader.points(reader.end_frame)[:, 1] - reader.points(reader.start_frame)[:, 1],
                                   -0.01 * (FRAMES - 1), atol=1e-6)
        assert main(["info", str(path)]) == 0
    assert main(["preview", str(good["usdc"]), "-o", str(tmp_path / "p.png"), "--size", "16", "16"]) == 0
    assert (tmp_path / "p.png").is_file()
    # a USD stage without authored start/end time codes: its frames are the points' time samples
    stage_path = tmp_path / "plain.usda"
    _stage("usda", lambda s: _mesh(s))[1](good, stage_path)
    reader = CacheReader(stage_path)
    assert (reader.start_frame, reader.end_frame) == (1, 2)
