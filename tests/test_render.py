"""Headless rendering: z-buffer, framing, orientation, colours and file output."""
from __future__ import annotations


import numpy as np
import pytest
from PIL import Image

import tpscore
from tpscore.showcase import render
from tpscore.showcase.datasets import face_height, make_face
from tpscore.showcase.render import (
    error_heatmap,
    fit_camera,
    grid_mesh,
    heatmap_colors,
    render_grid,
    render_mesh,
    save_gif,
    save_png,
    side_by_side,
)

WHITE = np.array([255, 255, 255])


def foreground(image, background=WHITE):
    return np.any(image != background, axis=2)


def face_grid_150():
    """A 150 x 150 grid over the average face (44k triangles)."""
    x, y = np.meshgrid(np.linspace(-60, 60, 150), np.linspace(90, -75, 150))
    return np.stack([x, y, face_height(None, x, y)], axis=-1)


def test_image_shape_and_dtype():
    image = render_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], width=120, height=80)
    assert image.shape == (80, 120, 3)
    assert image.dtype == np.uint8


def test_face_fills_the_expected_area_and_shading_varies():
    scan = make_face(spacing_mm=1.0)
    image = render_grid(scan.points, scan.valid, width=200, height=240)
    covered = foreground(image)
    rows, cols = np.nonzero(covered)
    # Framed with a 6 % margin on the tighter axis: the face spans most of it and is
    # centred.
    assert covered[120, 100] and not covered[2, 2] and not covered[-3, -3]
    assert abs(cols.mean() - 100) < 8 and abs(rows.mean() - 120) < 12
    assert rows.max() - rows.min() > 0.8 * 240
    # Shading reveals relief: the lit face is far from one flat colour.
    brightness = image[covered].mean(axis=1)
    assert brightness.std() > 10


def test_front_view_orientation():
    """+y is up in the picture and +x (the subject's left) is on the viewer's right."""
    frame = [[-10, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]]
    camera = fit_camera([np.array(frame, dtype=float)], width=100, height=100)
    upper_right = render_mesh([[2, 2, 0], [9, 2, 0], [9, 9, 0]], [[0, 1, 2]], camera=camera)
    rows, cols = np.nonzero(foreground(upper_right))
    assert rows.max() < 50 and cols.min() > 50


def test_left_view_shows_the_subjects_left_side():
    # A triangle at +x and one at -x, both facing the viewer in front view: seen from
    # the subject's left (view "left"), the +x one is in front and the nose (+z)
    # points to the viewer's left.
    vertices = np.array([[20, -5, 0], [20, 5, 0], [20, 0, 10],
                         [-20, -5, 0], [-20, 5, 0], [-20, 0, 10],
                         [0, 0, 30], [0, 1, 30], [1, 0, 30]], dtype=float)
    camera = fit_camera([vertices], view="left", width=100, height=100)
    view = camera.to_view(vertices)
    assert view[0, 2] > view[3, 2]           # the subject's left is nearer the viewer
    assert camera.to_pixels(view[6:7])[0, 0] < 50  # the nose points to the left


def test_front_most_triangle_wins_whatever_the_order():
    vertices = np.array([
        [-1, -1, 0], [1, -1, 0], [0, 1, 0],          # back, red
        [-1, -1, 5], [1, -1, 5], [0, 1, 5],          # front, blue
    ], dtype=float)
    colors = np.array([[1, 0, 0]] * 3 + [[0, 0, 1]] * 3, dtype=float)
    for faces in ([[0, 1, 2], [3, 4, 5]], [[3, 4, 5], [0, 1, 2]]):
        image = render_mesh(vertices, faces, colors=colors, width=60, height=60,
                            light=(0, 0, 1)).astype(int)
        centre = image[35, 30]
        assert centre[2] > 150 and centre[0] < 60, centre


def test_intersecting_triangles_resolve_per_pixel():
    # A tilted triangle crosses a flat one: each wins where it is nearer the viewer.
    vertices = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0],
                         [-1, -1, -1], [1, -1, 1], [0, 1, 0]], dtype=float)
    colors = np.array([[1, 0, 0]] * 3 + [[0, 0, 1]] * 3, dtype=float)
    image = render_mesh(vertices, [[0, 1, 2], [3, 4, 5]], colors=colors, width=80, height=80,
                        light=(0, 0, 1)).astype(int)
    left, right = image[60, 25], image[60, 55]
    assert left[0] > left[2] and right[2] > right[0]


def test_nan_vertices_and_their_triangles_are_skipped():
    points = face_grid_150()
    camera = fit_camera([points.reshape(-1, 3)], width=150, height=150)
    hole_centre = camera.to_pixels(camera.to_view(points[70:71, 70]))[0].astype(int)
    points[60:80, 60:80] = np.nan
    vertices, faces = grid_mesh(points)
    assert np.isnan(vertices[faces]).sum() == 0  # no triangle uses a missing vertex
    covered = foreground(render_mesh(vertices, faces, camera=camera))
    column, row = hole_centre
    assert not covered[row, column] and covered[row, column + 30]


def test_grid_mesh_triangles():
    points = face_grid_150()[:4, :5]
    vertices, faces = grid_mesh(points)
    assert faces.shape == (2 * 3 * 4, 3)
    # Counter-clockwise seen from +z: positive signed area in x, y.
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert (cross[:, 2] > 0).all()
    mask = np.ones((4, 5), dtype=bool)
    mask[0, 0] = False                       # one corner missing: that quad keeps one triangle
    _, fewer = grid_mesh(points, mask)
    assert len(fewer) == len(faces) - 1


def test_shared_camera_lines_pictures_up():
    points = face_grid_150()
    vertices, faces = grid_mesh(points)
    shifted = vertices + [0.0, 0.0, 3.0]     # same silhouette seen from the front
    camera = fit_camera([vertices, shifted], width=160, height=160)
    a = foreground(render_mesh(vertices, faces, camera=camera))
    b = foreground(render_mesh(shifted, faces, camera=camera))
    assert np.array_equal(a, b)
    smaller = vertices * 0.5
    alone = foreground(render_mesh(smaller, faces, width=160, height=160))
    shared = foreground(render_mesh(smaller, faces, camera=fit_camera([vertices, smaller],
                                                                      width=160, height=160)))
    assert shared.sum() < 0.5 * alone.sum()  # framed with the larger face, it looks smaller


def test_heatmap_colors_are_monotonic_in_lightness():
    rgb = heatmap_colors(np.linspace(0, 4, 200), vmax=4.0)
    assert rgb.shape == (200, 3) and rgb.min() >= 0 and rgb.max() <= 1
    lightness = rgb @ np.array([0.2126, 0.7152, 0.0722])
    assert np.all(np.diff(lightness) > 0)
    # Clipping above vmax, grey for NaN, default range [0, max].
    clipped = heatmap_colors([5.0, 9.0, np.nan], vmax=4.0)
    np.testing.assert_allclose(clipped[0], clipped[1])
    np.testing.assert_allclose(clipped[2], render.MISSING_VALUE_COLOR)
    np.testing.assert_allclose(heatmap_colors([0.0, 2.0])[1], heatmap_colors([4.0], vmax=4.0)[0])
    with pytest.raises(ValueError, match="cmap"):
        heatmap_colors([1.0], cmap="jet")


def test_grid_colors_follow_the_vertices():
    points = face_grid_150()
    values = np.where(points[..., 0] > 0, 1.0, 0.0)  # the subject's left half "hot"
    image = render_grid(points, colors=values, width=150, height=150, light=(0, 0, 1)).astype(int)
    hot, cold = heatmap_colors([1.0, 0.0], vmax=1.0) * 255
    right_half, left_half = image[75, 100], image[75, 50]
    # Lit head-on, the shade is albedo * (ambient + diffuse * n.z) plus specular: the
    # hue survives, so compare the colour directions.
    assert np.argmax(right_half) == np.argmax(hot) and np.argmax(left_half) == np.argmax(cold)


def test_error_heatmap_has_a_colour_bar():
    vertices, faces = grid_mesh(face_grid_150())
    errors = np.hypot(vertices[:, 0], vertices[:, 1]) / 30.0
    image = error_heatmap(vertices, faces, errors, width=300, height=200)
    assert image.shape == (200, 300, 3)
    bar = image[:, -render.COLORBAR_WIDTH:]
    # The bar's top shows the high end of the map and its bottom the low end.
    top = heatmap_colors([1.0], vmax=1.0)[0] * 255
    bottom = heatmap_colors([0.0], vmax=1.0)[0] * 255
    column = bar[:, 12].astype(float)
    assert np.min(np.abs(column - top).sum(axis=1)) < 6
    assert np.min(np.abs(column - bottom).sum(axis=1)) < 6
    with pytest.raises(ValueError, match="errors_mm"):
        error_heatmap(vertices, faces, errors[:-1])


def test_side_by_side_layout():
    a = np.zeros((50, 40, 3), dtype=np.uint8)
    b = np.full((30, 20, 3), 128, dtype=np.uint8)
    combined = side_by_side([a, b], ["first", "second"], title_height=20, gap=5)
    assert combined.shape == (70, 65, 3)
    np.testing.assert_array_equal(combined[20:70, 0:40], a)
    np.testing.assert_array_equal(combined[20:50, 45:65], b)
    assert (combined[:20] != 255).any()      # titles were drawn
    with pytest.raises(ValueError, match="titles"):
        side_by_side([a, b], ["only one"])


def test_png_round_trip(tmp_path):
    image = render_grid(face_grid_150(), width=90, height=70)
    path = tmp_path / "face.png"
    save_png(path, image)
    np.testing.assert_array_equal(np.asarray(Image.open(path).convert("RGB")), image)


def test_gif_has_every_frame_and_loops(tmp_path):
    vertices, faces = grid_mesh(face_grid_150())
    camera = fit_camera([vertices], width=80, height=80)
    frames = [render_mesh(vertices, faces, camera=camera,
                          light=(np.cos(angle), 0.3, 1.0)) for angle in np.linspace(0, 3, 5)]
    path = tmp_path / "anim.gif"
    save_gif(path, frames, fps=10)
    with Image.open(path) as gif:
        assert gif.n_frames == 5
        assert gif.info.get("loop") == 0
        assert gif.info.get("duration") == 100
        assert gif.size == (80, 80)
    with pytest.raises(ValueError, match="frames"):
        save_gif(tmp_path / "empty.gif", [])
    with pytest.raises(ValueError, match="fps"):
        save_gif(tmp_path / "bad.gif", frames, fps=0)


def test_a_150_grid_fills_the_picture():
    vertices, faces = grid_mesh(face_grid_150())
    assert len(faces) > 44_000
    image = render_mesh(vertices, faces, width=400, height=400)
    assert foreground(image).sum() > 0.5 * 400 * 400


@pytest.mark.parametrize("kwargs, name", [
    (dict(faces=[[0, 1, 7]]), "faces"),
    (dict(view="top"), "view"),
    (dict(width=0), "width"),
    (dict(light=(0, 0, 0)), "light"),
    (dict(colors=np.ones((2, 3))), "colors"),
])
def test_bad_input_is_rejected(kwargs, name):
    arguments = dict(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]])
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=name):
        render_mesh(**arguments)


def test_public_names_are_exported():
    for name in ("render_mesh", "render_grid", "heatmap_colors", "error_heatmap",
                 "side_by_side", "save_png", "save_gif", "fit_camera", "Camera"):
        assert name in render.__all__ and tpscore.render is render


def _plane(n=40, size=100.0):
    """An n x n grid on the plane z = 0 facing the viewer, rows from top to bottom."""
    x, y = np.meshgrid(np.linspace(-size / 2, size / 2, n), np.linspace(size / 2, -size / 2, n))
    points = np.stack([x, y, np.zeros_like(x)], axis=-1)
    uv = np.stack([(x + size / 2) / size, (size / 2 - y) / size], axis=-1)   # v down, as a scan's
    return points, uv


def test_texture_is_painted_where_its_uv_says():
    # the image's top left quarter is red, top right green, bottom left blue, bottom
    # right white: the picture's quarters are those colours, lit
    points, uv = _plane()
    texture = np.zeros((64, 64, 3), dtype=np.uint8)
    texture[:32, :32], texture[:32, 32:], texture[32:, :32], texture[32:, 32:] = (255, 0, 0), (0, 255, 0), \
        (0, 0, 255), (255, 255, 255)
    image = render_grid(points, texture=texture, uv=uv, width=200, height=200).astype(int)
    quarters = {"top left": image[40:80, 40:80], "top right": image[40:80, 120:160],
                "bottom left": image[120:160, 40:80], "bottom right": image[120:160, 120:160]}
    dominant = {name: int(np.argmax(q.reshape(-1, 3).mean(axis=0))) for name, q in quarters.items()}
    assert dominant == {"top left": 0, "top right": 1, "bottom left": 2, "bottom right": dominant["bottom right"]}
    assert quarters["bottom right"].min() > 150                       # white, lit
    assert quarters["top left"][..., 1:].max() < 20                   # pure red stays pure
    # detail finer than the vertex spacing survives: a texture line one pixel wide
    # between two vertices shows in the picture
    striped = np.full((400, 400, 3), 255, dtype=np.uint8)
    striped[:, 205] = 0   # between vertex columns (every 10 pixels of the texture)
    lined = render_grid(_plane(n=41)[0], texture=striped, uv=_plane(n=41)[1], width=400, height=400)
    assert lined[:, 180:230].min() < 120


def test_texture_needs_uv_and_excludes_colours():
    points, uv = _plane(n=5)
    texture = np.zeros((8, 8, 3), dtype=np.uint8)
    with pytest.raises(ValueError, match="needs uv"):
        render_grid(points, texture=texture)
    with pytest.raises(ValueError, match="not both"):
        render_grid(points, texture=texture, uv=uv, colors=(1, 0, 0))
    with pytest.raises(ValueError, match="only used with a texture"):
        render_grid(points, uv=uv)


def test_motion_map_draws_the_field_where_it_is():
    # the right half of a plane moves 4 mm to the right, the left half stays: colour
    # and arrows on the right only
    points, _ = _plane(n=60)
    motion = np.zeros_like(points)
    motion[..., 0] = np.where(points[..., 0] > 5, 4.0, 0.0)
    vertices, faces = grid_mesh(points)
    picture = render.motion_map(vertices, faces, motion.reshape(-1, 3), width=400, height=330)
    assert picture.shape == (330, 400, 3)
    mesh_part = picture[:, :330].astype(int)
    still, moving = mesh_part[60:270, 40:140], mesh_part[60:270, 190:290]
    # dark purple where still, yellow (the top of the colour map) where moving
    assert still[..., 2].mean() > still[..., 1].mean()
    assert moving[..., 0].mean() > 150 and moving[..., 1].mean() > 150
    # arrows are black, drawn on the moving half only
    black = (mesh_part.sum(axis=2) < 60)
    assert black[60:270, 40:140].sum() == 0 and black[60:270, 190:290].sum() > 50
    with pytest.raises(ValueError, match="displacement must have shape"):
        render.motion_map(vertices, faces, motion.reshape(-1, 3)[:10])
