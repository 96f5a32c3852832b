"""Scans given as meshes with their colours: textured OBJ (tpscore's own output among
them), PLY and GLB with vertex colours, and the warnings when colour cannot be used."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

import tpscore
from tpscore.expression.texture import track_texture
from tpscore.face import io
from tpscore.face.image import sample_image
from tpscore.showcase import datasets
from test_texture import textured_pair


def _write_landmarks(path, grid):
    # landmarks beside the mesh keep load_scan from warning that they are missing
    landmarks = np.full((22, 3), np.nan)
    landmarks[:3] = grid.points[grid.mask][[0, len(grid.points[grid.mask]) // 2, -1]]
    io.write_landmarks(path.with_suffix(".lm3"), landmarks)


def _load(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tpscore.LandmarkSnapWarning)
        return tpscore.load_scan(path, shape=(120, 120))


def _vertex_colours(grid, mesh):
    return np.round(sample_image(grid.image, mesh.uv)).astype(np.uint8)


def test_a_textured_obj_brings_its_image_and_uv(tmp_path):
    neutral, _ = textured_pair()
    mesh = neutral.mesh()
    path = tmp_path / "face.obj"
    io.write_textured_obj(path, mesh.vertices, mesh.faces, mesh.uv, neutral.image)
    _write_landmarks(path, neutral)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tpscore.ColourWarning)
        grid = _load(path)
    # the texture is used as it is: the same image, and every vertex's colour within
    # rounding of the image's (u,v through %.17g text and 1 - v twice)
    assert np.array_equal(grid.image, neutral.image)
    np.testing.assert_allclose(grid.colours[grid.mask], neutral.colours[neutral.mask], atol=1e-6)


@pytest.mark.parametrize("suffix", [".ply", ".glb"])
def test_vertex_colours_are_rendered_into_an_image(tmp_path, suffix):
    import trimesh

    neutral, _ = textured_pair()
    mesh = neutral.mesh()
    colours = _vertex_colours(neutral, mesh)
    path = tmp_path / f"face{suffix}"
    if suffix == ".ply":
        io.write_mesh(path, mesh.vertices, mesh.faces, vertex_colors=colours)
    else:
        trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=colours, process=False).export(path)
    _write_landmarks(path, neutral)
    grid = _load(path)
    assert grid.image is not None
    # each vertex's colour comes back through the 0.3 mm pixels around its place in the
    # image, blended with its neighbours' over a fraction of a pixel: on a pattern of 1-4
    # mm wavelength that is a small part of the pattern's own spread, and the colours
    # follow the vertices' closely (a misplaced u,v would decorrelate them)
    got, want = grid.colours[grid.mask][:, 0], neutral.colours[neutral.mask][:, 0]
    assert np.median(np.abs(got - want)) < 0.15 * np.std(want)
    assert np.corrcoef(got, want)[0, 1] > 0.97


def test_the_tracker_follows_the_skin_of_textured_meshes(tmp_path):
    neutral, expressive = textured_pair()
    from_bnt = track_texture(neutral, expressive)
    paths = []
    for name, grid in (("neutral", neutral), ("expressive", expressive)):
        mesh = grid.mesh()
        path = tmp_path / f"{name}.ply"
        io.write_mesh(path, mesh.vertices, mesh.faces, vertex_colors=_vertex_colours(grid, mesh))
        _write_landmarks(path, grid)
        paths.append(path)
    loaded = [_load(path) for path in paths]
    matches = track_texture(*loaded)
    assert matches is not None
    # vertex colours hold the pattern only at the vertices: most of what the images match
    assert matches.matched_fraction > 0.8 * from_bnt.matched_fraction


def test_a_missing_texture_warns_and_reads_without_colour(tmp_path):
    neutral, _ = textured_pair()
    mesh = neutral.mesh()
    path = tmp_path / "face.obj"
    _, mtl, png = io.write_textured_obj(path, mesh.vertices, mesh.faces, mesh.uv, neutral.image)
    _write_landmarks(path, neutral)
    png.unlink()
    with pytest.warns(tpscore.ColourWarning, match="texture image cannot be used"):
        assert _load(path).image is None
    png.write_bytes(b"not a png at all")
    with pytest.warns(tpscore.ColourWarning, match="texture image cannot be used"):
        assert _load(path).image is None
    mtl.write_text("newmtl skin\nKd 1 1 1\n")
    with pytest.warns(tpscore.ColourWarning, match="names no texture image"):
        assert _load(path).image is None
    mtl.unlink()
    with pytest.warns(tpscore.ColourWarning, match="material library cannot be read"):
        grid = _load(path)
    # the geometry is read all the same
    assert grid.image is None and grid.n_valid == neutral.n_valid


def test_a_mesh_without_colour_reads_quietly_and_without_image(tmp_path):
    neutral, _ = textured_pair()
    mesh = neutral.mesh()
    path = tmp_path / "face.ply"
    io.write_mesh(path, mesh.vertices, mesh.faces)
    _write_landmarks(path, neutral)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tpscore.ColourWarning)
        assert _load(path).image is None


def test_a_transfer_from_scans_without_colour_warns():
    scans = datasets.demo_triplet("12")
    grids = [tpscore.resample_scan(scan.points, scan.landmarks) for scan in scans]
    with pytest.warns(tpscore.TextureWarning, match="neither source scan has a colour image"):
        tpscore.transfer(*grids, "12")


def test_a_texture_that_does_not_map_x_y_squarely_is_rendered(tmp_path):
    # every other column of the image: its pixels twice as tall as wide on the face, as
    # in a texture atlas, so the u,v cannot serve the tracker and the colours are
    # rendered into an image of square pixels over x, y
    neutral, _ = textured_pair()
    mesh = neutral.mesh()
    squeezed = np.ascontiguousarray(neutral.image[:, ::2])
    path = tmp_path / "atlas.obj"
    io.write_textured_obj(path, mesh.vertices, mesh.faces, mesh.uv, squeezed)
    _write_landmarks(path, neutral)
    grid = _load(path)
    assert grid.image is not None and grid.image.shape != squeezed.shape
    want = sample_image(squeezed, mesh.uv)[:, 0]
    got = grid.colours[grid.mask][:, 0] * 255
    # as for vertex colours: the texture comes back through 0.3 mm pixels
    assert np.corrcoef(got, want)[0, 1] > 0.97


def test_a_glb_texture_is_read(tmp_path):
    import trimesh
    from PIL import Image

    neutral, _ = textured_pair()
    mesh = neutral.mesh()
    visual = trimesh.visual.TextureVisuals(uv=np.column_stack([mesh.uv[:, 0], 1.0 - mesh.uv[:, 1]]),
                                           image=Image.fromarray(neutral.image))
    path = tmp_path / "face.glb"
    trimesh.Trimesh(mesh.vertices, mesh.faces, visual=visual, process=False).export(path)
    _write_landmarks(path, neutral)
    grid = _load(path)
    assert grid.image is not None
    got, want = grid.colours[grid.mask][:, 0], neutral.colours[neutral.mask][:, 0]
    assert np.corrcoef(got, want)[0, 1] > 0.97
