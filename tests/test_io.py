"""Readers and writers: round trips, and clear errors for broken files."""
from __future__ import annotations

import json
import struct
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from tpscore import (
    BntScan,
    read_bnt,
    read_landmarks,
    read_lm3,
    read_mesh,
    write_bnt,
    write_landmarks,
    write_lm3,
    write_mesh,
)
from tpscore.face.io import write_textured_obj
from tpscore.face.landmarks import LANDMARK_NAMES

ZMIN = -1.0e9


def make_bnt_scan(nrows=12, ncols=9, seed=0, name="bs999_N_N_0.png") -> BntScan:
    """A small scan laid out like make_scans.py writes them, with background and a hole."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:nrows, 0:ncols]
    points = np.stack([-3.0 + 0.7 * cols, 4.0 - 0.7 * rows, rng.normal(50.0, 5.0, (nrows, ncols))], axis=-1)
    uv = np.stack([(cols + 0.5) / ncols, (rows + 0.5) / nrows], axis=-1)
    valid = np.ones((nrows, ncols), dtype=bool)
    valid[0, :] = False           # background band
    valid[:, -1] = False
    valid[5, 4] = False           # a hole
    points[~valid] = np.nan
    return BntScan(nrows, ncols, ZMIN, name, points, uv.astype(np.float64), valid)


def bnt_bytes(nrows, ncols, name=b"x.png", len2=None, values=None, zmin=ZMIN, extra=b""):
    """Raw .bnt bytes, for building broken files."""
    if values is None:
        values = np.zeros(5 * nrows * ncols)
    len2 = 5 * nrows * ncols if len2 is None else len2
    head = struct.pack("<HHdH", nrows, ncols, zmin, len(name)) + name + struct.pack("<I", len2)
    return head + np.asarray(values, "<f8").tobytes() + extra


def some_landmarks(seed=1, missing=(4, 21)):
    landmarks = np.random.default_rng(seed).normal(0.0, 40.0, (22, 3))
    landmarks[list(missing)] = np.nan
    return landmarks


# --------------------------------------------------------------------------- .bnt

def test_bnt_round_trip_is_bit_exact(tmp_path):
    scan = make_bnt_scan()
    path = tmp_path / "scan.bnt"
    write_bnt(path, scan)
    back = read_bnt(path)
    assert (back.nrows, back.ncols, back.zmin, back.image_name) == (scan.nrows, scan.ncols, ZMIN, scan.image_name)
    assert np.array_equal(back.valid, scan.valid)
    assert np.array_equal(back.points, scan.points, equal_nan=True)
    assert np.array_equal(back.uv, scan.uv)
    again = tmp_path / "again.bnt"
    write_bnt(again, back)
    assert again.read_bytes() == path.read_bytes()
    assert back.n_valid == scan.valid.sum()
    assert np.array_equal(back.valid_points(), scan.points[scan.valid])


def test_bnt_layout_matches_the_format(tmp_path):
    """Decode the file by hand from the documented layout: column after column, point r*ncols + c."""
    scan = make_bnt_scan()
    path = tmp_path / "scan.bnt"
    write_bnt(path, scan)
    raw = path.read_bytes()
    nrows, ncols, zmin, name_len = struct.unpack_from("<HHdH", raw, 0)
    (len2,) = struct.unpack_from("<I", raw, 14 + name_len)
    data = np.frombuffer(raw, "<f8", offset=18 + name_len).reshape(5, -1).T
    assert (nrows, ncols, zmin, len2) == (scan.nrows, scan.ncols, ZMIN, 5 * scan.nrows * scan.ncols)
    r, c = 3, 2
    assert np.array_equal(data[r * ncols + c, :3], scan.points[r, c])
    assert np.all(data[0 * ncols + 1, :3] == ZMIN)  # background: x = y = z = zmin


def test_bnt_reads_make_scans_output(shared, tmp_path):
    subprocess.run([sys.executable, str(shared / "tools" / "make_scans.py"), str(tmp_path),
                    "--subjects", "0", "--expressions", "N_N_0"], check=True, capture_output=True)
    base = tmp_path / "bs000" / "bs000_N_N_0"
    scan = read_bnt(base.with_suffix(".bnt"))
    truth = np.load(str(base) + "_gt.npz")
    assert scan.image_name == "bs000_N_N_0.png"
    assert np.array_equal(scan.valid, truth["valid_mask"])
    assert 30_000 < scan.n_valid < 45_000
    rows, cols = np.nonzero(scan.valid)
    spacing, x0, y_top = float(truth["grid_spacing_mm"]), float(truth["grid_x0"]), float(truth["grid_y_top"])
    # Pixel centres are x0 + c s and y_top - r s, computed the same way by the writer.
    assert np.allclose(scan.points[rows, cols, 0], x0 + spacing * cols, atol=1e-9)
    assert np.allclose(scan.points[rows, cols, 1], y_top - spacing * rows, atol=1e-9)
    assert np.array_equal(np.floor(scan.uv[..., 0] * scan.ncols), np.mgrid[0:scan.nrows, 0:scan.ncols][1])
    copy = tmp_path / "copy.bnt"
    write_bnt(copy, scan)
    assert copy.read_bytes() == base.with_suffix(".bnt").read_bytes()

    landmarks, names = read_lm3(base.with_suffix(".lm3"), return_names=True)
    written = truth["landmarks_written"]
    assert np.array_equal(np.isfinite(landmarks).all(axis=1), written)
    assert names == [n for n, w in zip(LANDMARK_NAMES, written) if w]
    # the generator writes 4 decimals
    assert np.allclose(landmarks[written], truth["landmarks_noisy"][written], atol=5.1e-5)


def test_bnt_truncated_at_any_offset_names_file_and_problem(tmp_path):
    scan = make_bnt_scan()
    full = tmp_path / "full.bnt"
    write_bnt(full, scan)
    raw = full.read_bytes()
    name_len = len(scan.image_name)
    offsets = [0, 1, 3, 13, 14, 14 + name_len - 1, 14 + name_len + 2, 18 + name_len,
               18 + name_len + 7, len(raw) // 2, len(raw) - 8, len(raw) - 1]
    for offset in offsets:
        path = tmp_path / f"cut_{offset}.bnt"
        path.write_bytes(raw[:offset])
        with pytest.raises(ValueError, match="truncated") as error:
            read_bnt(path)
        assert path.name in str(error.value)


@pytest.mark.parametrize(
    "content, problem",
    [
        (bnt_bytes(3, 4, len2=59), "len2 = 59 is not 5"),
        (bnt_bytes(0, 4), "empty"),
        (bnt_bytes(3, 0), "empty"),
        # product that does not fit the file: the header claims a huge grid
        (bnt_bytes(60000, 60000, len2=0, values=[]), "len2 = 0 is not 5"),
        (bnt_bytes(1000, 1000, values=np.zeros(50)), "truncated .bnt data: 1000 x 1000 points need"),
        (bnt_bytes(3, 4)[:-8] + b"", "truncated"),
        (bnt_bytes(3, 4, extra=b"\0\0\0"), "3 trailing bytes"),
        (bnt_bytes(3, 4, name=b"\xff\xfe\x00garbage"), "not printable ASCII"),
        (bnt_bytes(3, 4, zmin=float("nan")), "zmin"),
        (bnt_bytes(2, 2, values=[1, 2, np.nan, 4, 0, 0, 0, 0, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0]),
         "NaN or infinite"),
    ],
)
def test_bnt_inconsistent_files(tmp_path, content, problem):
    path = tmp_path / "broken.bnt"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=problem) as error:
        read_bnt(path)
    assert "broken.bnt" in str(error.value)


def test_bnt_background_with_nan_is_accepted(tmp_path):
    # Only valid points must be finite: u,v at background may be anything.
    values = np.concatenate([[ZMIN, 1.0, ZMIN, 2.0], [ZMIN, 3.0, ZMIN, 4.0], [ZMIN, 5.0, ZMIN, 6.0],
                             [np.nan, 0.5, np.nan, 0.5], [np.nan, 0.5, np.nan, 0.5]])
    path = tmp_path / "bg.bnt"
    path.write_bytes(bnt_bytes(2, 2, values=values))
    scan = read_bnt(path)
    assert scan.valid.tolist() == [[False, True], [False, True]]
    assert scan.points[1, 1].tolist() == [2.0, 4.0, 6.0]


def test_bnt_missing_file():
    with pytest.raises(ValueError, match="not found"):
        read_bnt("/nonexistent/folder/scan.bnt")


def test_write_bnt_rejects_bad_scans(tmp_path):
    scan = make_bnt_scan()
    scan.points[2, 2, 2] = np.nan  # a valid point without z
    with pytest.raises(ValueError, match="valid points"):
        write_bnt(tmp_path / "bad.bnt", scan)
    assert not list(tmp_path.iterdir())  # nothing written, no temporary left


# --------------------------------------------------------------------------- .lm3

def test_lm3_round_trip_with_missing_landmarks(tmp_path):
    landmarks = some_landmarks()
    path = tmp_path / "a.lm3"
    write_lm3(path, landmarks)
    back, names = read_lm3(path, return_names=True)
    assert np.array_equal(back, landmarks, equal_nan=True)  # repr() text reads back exactly
    assert names == [n for i, n in enumerate(LANDMARK_NAMES) if i not in (4, 21)]
    lines = path.read_text().splitlines()
    assert lines[1] == "" and lines[2] == "20 landmarks:" and lines[3] == LANDMARK_NAMES[0]


def test_lm3_star_comment_header_and_crlf(tmp_path):
    text = ("Bosphorus landmarks\r\n*\r\nfree text\r\nmore text\r\n\r\n2 landmarks:\r\n"
            "Nose tip\r\n1.5 2 -3e1\r\nchin middle\r\n0 0 0\r\n\r\n")
    path = tmp_path / "b.lm3"
    path.write_bytes(text.encode())
    landmarks = read_landmarks(path)
    assert landmarks[13].tolist() == [1.5, 2.0, -30.0]
    assert landmarks[21].tolist() == [0.0, 0.0, 0.0]
    assert np.isnan(landmarks[:13]).all()


def test_lm3_with_the_ear_lobes_keeps_the_22(tmp_path):
    # the database labels up to 24 landmarks: the two ear lobes beyond the 22
    pairs = [("Left ear lobe", "70 -10 20"), ("Nose tip", "1 2 3"), ("Right ear lobe", "-70 -10 20"),
             ("Chin middle", "0 -60 10")]
    path = tmp_path / "ears.lm3"
    path.write_text(lm3_text(4, pairs))
    landmarks, names = read_lm3(path, return_names=True)
    assert names == ["Nose tip", "Chin middle"]
    assert landmarks[13].tolist() == [1.0, 2.0, 3.0] and np.isfinite(landmarks).all(axis=1).sum() == 2
    full = [(name, f"{i} 0 0") for i, name in enumerate(LANDMARK_NAMES)] + pairs[::2]
    path.write_text(lm3_text(24, full))
    assert np.isfinite(read_lm3(path)).all()
    path.write_text(lm3_text(2, [pairs[0], pairs[0]]))
    with pytest.raises(ValueError, match="duplicate landmark 'Left ear lobe'"):
        read_lm3(path)


def lm3_text(count, pairs):
    body = "\n".join(f"{name}\n{coords}" for name, coords in pairs)
    return f"3D landmark points\n\n{count} landmarks:\n{body}\n"


@pytest.mark.parametrize(
    "text, problem, line",
    [
        (lm3_text(1, [("Nose top", "1 2 3")]), "unknown landmark name 'Nose top'", 4),
        (lm3_text(2, [("Nose tip", "1 2 3"), ("nose tip", "1 2 3")]), "duplicate landmark", 6),
        (lm3_text(2, [("Nose tip", "1 2 3")]), "announces 2 landmarks but lists only 1", None),
        (lm3_text(1, [("Nose tip", "1 2 3"), ("Chin middle", "1 2 3")]), "more content", 6),
        (lm3_text(1, [("Nose tip", "1 2 x")]), "expected 'x y z'", 5),
        (lm3_text(1, [("Nose tip", "1 2")]), "expected 'x y z'", 5),
        (lm3_text(1, [("Nose tip", "1 nan 3")]), "non-finite", 5),
        ("header\n\nlandmarks: 3\n", "expected '<N> landmarks:'", 3),
        ("header\nno empty line\n1 landmarks:\n", "expected an empty line", 2),
        ("", "empty", None),
    ],
)
def test_lm3_errors_name_file_and_line(tmp_path, text, problem, line):
    path = tmp_path / "bad.lm3"
    path.write_text(text)
    with pytest.raises(ValueError, match=problem) as error:
        read_lm3(path)
    assert "bad.lm3" in str(error.value)
    if line is not None:
        assert f"line {line}:" in str(error.value)


def test_write_lm3_rejects_partial_rows_and_wrong_shape(tmp_path):
    landmarks = some_landmarks()
    landmarks[0, 1] = np.nan
    with pytest.raises(ValueError, match="row 0"):
        write_lm3(tmp_path / "x.lm3", landmarks)
    with pytest.raises(ValueError, match=r"shape \(22, 3\)"):
        write_lm3(tmp_path / "x.lm3", np.zeros((21, 3)))


def test_failed_write_leaves_previous_file(tmp_path):
    path = tmp_path / "keep.lm3"
    write_lm3(path, some_landmarks())
    before = path.read_bytes()
    with pytest.raises(ValueError):
        write_lm3(path, np.full((22, 3), np.inf))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.lm3"]
    with pytest.raises(ValueError, match="does not exist"):
        write_lm3(tmp_path / "no" / "such.lm3", some_landmarks())


# --------------------------------------------------------------------------- CSV / JSON

@pytest.mark.parametrize("suffix", [".lm3", ".csv", ".json"])
def test_landmark_round_trips(tmp_path, suffix):
    landmarks = some_landmarks(seed=3, missing=(0, 7, 13))
    path = tmp_path / f"lm{suffix}"
    write_landmarks(path, landmarks)
    assert np.array_equal(read_landmarks(path), landmarks, equal_nan=True)


def test_csv_variants(tmp_path):
    named = tmp_path / "named.csv"
    named.write_text("Chin middle,1,2,3\nnose TIP, 4, 5, 6\n")
    landmarks = read_landmarks(named)
    assert landmarks[21].tolist() == [1, 2, 3] and landmarks[13].tolist() == [4, 5, 6]
    assert np.isnan(landmarks[0]).all()

    rows = [f"{i},{i + 0.5},{-i}" for i in range(22)]
    rows[3] = ",,"
    rows[5] = "nan,nan,nan"
    positional = tmp_path / "positional.csv"
    positional.write_text("x,y,z\n" + "\n".join(rows) + "\n")
    landmarks = read_landmarks(positional)
    assert landmarks[10].tolist() == [10, 10.5, -10]
    assert np.isnan(landmarks[[3, 5]]).all() and np.isfinite(np.delete(landmarks, [3, 5], 0)).all()


@pytest.mark.parametrize(
    "text, problem",
    [
        ("name,x,y,z\nNose tip,1,2,3\nNose tip,1,2,3\n", "line 3: duplicate landmark"),
        ("name,x,y,z\nNose tap,1,2,3\n", "line 2: unknown landmark name"),
        ("1,2,3\n4,5,6\n", "must have 22 rows"),
        ("Nose tip,1,2\n", "line 1: expected 3 coordinates"),
        ("Nose tip,1,two,3\n", "line 1: unparsable"),
        ("Nose tip,1,nan,3\n", "line 1: non-finite"),
    ],
)
def test_csv_errors(tmp_path, text, problem):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=problem) as error:
        read_landmarks(path)
    assert "bad.csv" in str(error.value)


def test_json_variants_and_errors(tmp_path):
    path = tmp_path / "list.json"
    entries = [[i, 2 * i, 3.5] for i in range(22)]
    entries[2] = None
    path.write_text(json.dumps(entries))
    landmarks = read_landmarks(path)
    assert np.isnan(landmarks[2]).all() and landmarks[3].tolist() == [3, 6, 3.5]

    path = tmp_path / "dict.json"
    path.write_text(json.dumps({"Nose tip": [1, 2, 3], "Chin middle": None}))
    landmarks = read_landmarks(path)
    assert landmarks[13].tolist() == [1, 2, 3] and np.isnan(np.delete(landmarks, 13, 0)).all()

    for text, problem in [('{"Nose tup": [1, 2, 3]}', "unknown landmark name"),
                          ('{"Nose tip": [1, 2]}', r"\[x, y, z\]"),
                          ('{"Nose tip": [1, 2, 3], "nose tip": [1, 2, 3]}', "duplicate"),
                          ("[[1, 2, 3]]", "22 entries"),
                          ('{"Nose tip": [1, 2, 3]', "invalid JSON")]:
        path = tmp_path / "bad.json"
        path.write_text(text)
        with pytest.raises(ValueError, match=problem) as error:
            read_landmarks(path)
        assert "bad.json" in str(error.value)


def test_landmarks_unknown_suffix(tmp_path):
    with pytest.raises(ValueError, match="unknown landmark file type"):
        read_landmarks(tmp_path / "x.txt")
    with pytest.raises(ValueError, match="unknown landmark file type"):
        write_landmarks(tmp_path / "x.txt", some_landmarks())


# --------------------------------------------------------------------------- meshes

def small_mesh(seed=0):
    rng = np.random.default_rng(seed)
    vertices = rng.normal(0.0, 30.0, (7, 3))
    faces = np.array([[0, 1, 2], [2, 3, 0], [3, 4, 5], [5, 6, 3]])
    uv = rng.random((7, 2))
    colors = rng.integers(0, 256, (7, 3)).astype(np.uint8)
    return vertices, faces, uv, colors


def test_obj_round_trip_with_uv_and_colors(tmp_path):
    vertices, faces, uv, colors = small_mesh()
    path = tmp_path / "m.obj"
    write_mesh(path, vertices, faces, uv=uv, vertex_colors=colors)
    loaded = trimesh.load(str(path), process=False, maintain_order=True)
    assert np.array_equal(loaded.vertices, vertices)  # %.17g is exact for float64
    assert np.array_equal(loaded.faces, faces)
    assert np.array_equal(loaded.visual.uv, uv)
    ours_vertices, ours_faces = read_mesh(path)
    assert np.array_equal(ours_vertices, vertices) and np.array_equal(ours_faces, faces)
    colour_line = path.read_text().splitlines()[1].split()
    assert np.allclose([float(v) for v in colour_line[4:7]], colors[0] / 255.0, atol=1e-6)


def test_ply_round_trip_with_uv_and_colors(tmp_path):
    vertices, faces, uv, colors = small_mesh(seed=1)
    path = tmp_path / "m.ply"
    write_mesh(path, vertices, faces, uv=uv, vertex_colors=colors)
    loaded = trimesh.load(str(path), process=False, fix_texture=False)
    assert np.array_equal(loaded.vertices, vertices)  # stored as float64
    assert np.array_equal(loaded.faces, faces)
    assert np.array_equal(loaded.visual.uv, uv)
    assert "property double texture_u" in path.read_bytes()[:600].decode("ascii", "replace")
    plain = tmp_path / "c.ply"
    write_mesh(plain, vertices, faces, vertex_colors=colors)
    loaded = trimesh.load(str(plain), process=False)
    assert np.array_equal(loaded.visual.vertex_colors[:, :3], colors)


def test_read_mesh_keeps_unused_vertices_and_order(tmp_path):
    vertices, faces, uv, _ = small_mesh(seed=2)
    faces = faces[:2]  # vertices 4, 5, 6 unused
    for suffix in (".obj", ".ply"):
        path = tmp_path / f"m{suffix}"
        write_mesh(path, vertices, faces, uv=uv)
        got_vertices, got_faces = read_mesh(path)
        assert np.array_equal(got_vertices, vertices), suffix
        assert np.array_equal(got_faces, faces), suffix


def test_point_clouds_and_other_formats(tmp_path):
    vertices, faces, _, _ = small_mesh(seed=3)
    cloud = tmp_path / "cloud.ply"
    write_mesh(cloud, vertices, np.empty((0, 3), dtype=int))
    got_vertices, got_faces = read_mesh(cloud)
    assert np.array_equal(got_vertices, vertices) and got_faces.shape == (0, 3)
    obj_cloud = tmp_path / "cloud.obj"
    write_mesh(obj_cloud, vertices, [])
    assert read_mesh(obj_cloud)[1].shape == (0, 3)
    stl = tmp_path / "m.stl"
    trimesh.Trimesh(vertices, faces, process=False).export(str(stl))
    stl_vertices, stl_faces = read_mesh(stl)
    # STL stores float32 corners per triangle
    assert np.allclose(stl_vertices[stl_faces], vertices[faces], atol=1e-4)


def test_read_mesh_errors(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        read_mesh(tmp_path / "missing.ply")
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nthis is not a ply header\n\x00\x01")
    with pytest.raises(ValueError, match="garbage.ply"):
        read_mesh(garbage)
    bad_obj = tmp_path / "bad.obj"
    bad_obj.write_text("v 0 0 0\nv 1 0 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="line 3"):
        read_mesh(bad_obj)


def test_write_mesh_rejects_bad_input(tmp_path):
    vertices, faces, uv, _ = small_mesh()
    bad = vertices.copy()
    bad[2, 0] = np.nan
    with pytest.raises(ValueError, match="vertices contains NaN"):
        write_mesh(tmp_path / "m.obj", bad, faces)
    with pytest.raises(ValueError, match="faces refers to vertex indices"):
        write_mesh(tmp_path / "m.obj", vertices, faces + 5)
    with pytest.raises(ValueError, match="uv must have shape"):
        write_mesh(tmp_path / "m.obj", vertices, faces, uv=uv[:3])
    with pytest.raises(ValueError, match=r"\.obj or \.ply"):
        write_mesh(tmp_path / "m.stl", vertices, faces)
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------- textures

def quadrant_image(height=40, width=60) -> np.ndarray:
    """Red top left, green top right, blue bottom left, white bottom right."""
    image = np.zeros((height, width, 3), dtype=np.uint8)
    image[: height // 2, : width // 2] = (255, 0, 0)
    image[: height // 2, width // 2:] = (0, 255, 0)
    image[height // 2:, : width // 2] = (0, 0, 255)
    image[height // 2:, width // 2:] = 255
    return image


def test_textured_obj_reads_back_with_its_colours_where_they_belong(tmp_path):
    # a 4 x 4 grid of vertices whose u,v (tpscore's convention: v DOWN) lie in the
    # middle of the image's quadrants: the top rows of vertices must come out red and
    # green, the bottom ones blue and white, whatever convention the OBJ uses inside
    u, v = np.meshgrid([0.2, 0.3, 0.7, 0.8], [0.2, 0.3, 0.7, 0.8])
    uv = np.column_stack([u.ravel(), v.ravel()])
    vertices = np.column_stack([u.ravel() * 100, -v.ravel() * 100, np.zeros(16)])
    index = np.arange(16).reshape(4, 4)
    faces = np.concatenate([np.column_stack([index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel()]),
                            np.column_stack([index[:-1, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()])])
    obj, mtl, png = write_textured_obj(tmp_path / "face.obj", vertices, faces, uv, quadrant_image())
    assert (obj.name, mtl.name, png.name) == ("face.obj", "face.mtl", "face_texture.png")
    assert "map_Kd face_texture.png" in mtl.read_text() and "mtllib face.mtl" in obj.read_text()
    loaded = trimesh.load(str(obj), process=False, maintain_order=True)
    assert np.allclose(loaded.vertices, vertices)
    assert loaded.visual.material.image.size == (60, 40)
    colours = loaded.visual.to_color().vertex_colors[:, :3].reshape(4, 4, 3)
    expected = np.array([[[255, 0, 0]] * 2 + [[0, 255, 0]] * 2] * 2 + [[[0, 0, 255]] * 2 + [[255, 255, 255]] * 2] * 2)
    np.testing.assert_array_equal(colours, expected)


def test_textured_obj_of_a_scan_shows_its_photograph(tmp_path):
    # a demo scan's grid, written as a textured mesh and read back by trimesh: each
    # vertex's colour is the scan's colour at that vertex
    from tpscore import load_scan
    from tpscore.showcase import demo_faces

    scan = demo_faces.make_demo_scan(2, None, seed=4)
    grid = load_scan(scan.write(tmp_path, "scan"))
    mesh = grid.mesh()
    obj, _, _ = write_textured_obj(tmp_path / "mesh.obj", mesh.vertices, mesh.faces, mesh.uv, grid.image)
    loaded = trimesh.load(str(obj), process=False, maintain_order=True)
    assert len(loaded.vertices) == len(mesh.vertices)
    read_back = loaded.visual.to_color().vertex_colors[:, :3] / 255.0
    expected = grid.colours.reshape(-1, 3)[mesh.grid_index]
    # trimesh picks the nearest pixel, tpscore interpolates: a few levels apart at most
    # on smooth skin, more at the sharp edges of brows and lips
    difference = np.abs(read_back - expected).max(axis=1)
    assert np.median(difference) < 0.03 and np.mean(difference < 0.1) > 0.97


def test_textured_obj_rejects_bad_input_and_writes_nothing(tmp_path):
    vertices, faces, uv, _ = small_mesh()
    image = quadrant_image()
    with pytest.raises(ValueError, match="writes an .obj"):
        write_textured_obj(tmp_path / "m.ply", vertices, faces, uv, image)
    with pytest.raises(ValueError, match="uv must have shape"):
        write_textured_obj(tmp_path / "m.obj", vertices, faces, uv[:3], image)
    with pytest.raises(ValueError, match="image must"):
        write_textured_obj(tmp_path / "m.obj", vertices, faces, uv, image.astype(float))
    with pytest.raises(ValueError, match="material"):
        write_textured_obj(tmp_path / "m.obj", vertices, faces, uv, image, material="a b")
    assert not list(tmp_path.iterdir())


def test_reprs_are_one_line_summaries():
    scan = make_bnt_scan()
    text = repr(scan)
    assert text == f"BntScan(12x9, {scan.n_valid} valid points, image 'bs999_N_N_0.png')"
