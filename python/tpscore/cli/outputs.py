"""What the command line writes for a transfer, in the target's colours: the animated
target as a textured OBJ or a coloured PLY, a picture of every stage side by side, a GIF
of a magnitude sweep and a page to open in a browser. ``tpscore transfer`` and ``tpscore
demo`` write the same things the same way."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..face import io
from ..showcase import render, viewer

__all__ = ["write_result_mesh", "transfer_picture", "write_sweep_gif", "write_result_page"]

PANEL_SIZE = 400


def write_result_mesh(result, path) -> list[Path]:
    """The animated target as ``.obj`` (with its ``.mtl`` and the target's photograph as
    ``_texture.png`` when the target has one) or ``.ply`` (with vertex colours); returns
    the files written."""
    path = Path(path)
    mesh = result.mesh()  # an opened mouth is an opening in the mesh
    if path.suffix.lower() == ".obj" and result.image is not None:
        return list(io.write_textured_obj(path, mesh.vertices, mesh.faces, mesh.uv, result.image))
    if result.colours is not None:
        # the colours themselves, without u,v: a PLY names no image, and readers such as
        # trimesh show texture coordinates rather than colours when a file has both
        colours = result.colours.reshape(-1, 3)[mesh.grid_index]
        io.write_mesh(path, mesh.vertices, mesh.faces, vertex_colors=colours)
    else:
        # OBJ and PLY viewers put v = 0 at the bottom of an image; a scan's v runs down
        uv = np.column_stack([mesh.uv[:, 0], 1.0 - mesh.uv[:, 1]])
        io.write_mesh(path, mesh.vertices, mesh.faces, uv=uv)
    return [path]


def _render(points, mask, grid, camera=None, triangles=None) -> np.ndarray:
    """A face in its own colours where it has them, else clay; ``triangles`` (flat grid
    indices) replace the grid's own (a result's, which leave an opened mouth open)."""
    options = dict(camera=camera) if camera is not None else dict(width=PANEL_SIZE, height=PANEL_SIZE)
    if grid.image is not None:
        options.update(texture=grid.image, uv=grid.uv)
    if triangles is None:
        return render.render_grid(points, mask, **options)
    vertices = np.where(np.asarray(mask)[..., None], points, np.nan).reshape(-1, 3)
    if "uv" in options:
        options["uv"] = np.asarray(options["uv"]).reshape(-1, 2)
    return render.render_mesh(vertices, triangles, **options)


def transfer_picture(grids, result, *, errors=None, error_vmax: float | None = None,
                     titles: dict | None = None) -> np.ndarray:
    """Source neutral, source expressive, the source's measured motion, target neutral,
    result and (given per-vertex `errors`, (H, W) mm on the target grid) the error heat
    map, side by side. The target and the result share one framing, so they line up.

    `titles` may replace the panels' default titles by key: "source", "expressive",
    "motion", "target", "result", "error".
    """
    source, expressive, _ = grids   # the target is drawn from the result, in its framing
    labels = "+".join(result.animation.labels)
    magnitude = result.magnitude if np.isscalar(result.magnitude) else None
    names = {"source": "source neutral", "expressive": "source expressive",
             "motion": "source's measured motion (mm)", "target": "target neutral",
             "result": f"target {labels}" + (f" m={magnitude:g}" if magnitude is not None else ""),
             "error": "error (mm)"}
    names.update(titles or {})
    panels = [_render(source.points, source.mask, source), _render(expressive.points, expressive.mask, expressive)]
    keys = ["source", "expressive"]
    motion = result.measured_motion()
    if motion is not None:
        grid = result.model.source.grid
        vertices, faces = render.grid_mesh(grid.points, grid.mask)
        panels.append(render.motion_map(vertices, faces, motion.reshape(-1, 3), width=PANEL_SIZE,
                                        height=PANEL_SIZE))
        keys.append("motion")
    camera = render.fit_camera([result.neutral[result.mask], result.vertices[result.mask]],
                               width=PANEL_SIZE, height=PANEL_SIZE)
    panels.append(_render(result.neutral, result.mask, result.target.grid, camera))
    panels.append(_render(result.vertices, result.mask, result.target.grid, camera, result.triangles()))
    keys += ["target", "result"]
    if errors is not None:
        mesh = result.mesh()
        error_camera = render.fit_camera([mesh.vertices], width=PANEL_SIZE - render.COLORBAR_WIDTH,
                                         height=PANEL_SIZE)
        panels.append(render.error_heatmap(mesh.vertices, mesh.faces,
                                           np.asarray(errors, dtype=np.float64).reshape(-1)[mesh.grid_index],
                                           vmax=error_vmax, camera=error_camera))
        keys.append("error")
    return render.side_by_side(panels, [names[k] for k in keys])


def write_sweep_gif(result, path, *, frames: int = 18, fps: float = 12.0) -> None:
    """A GIF of the target going from neutral to the result (its magnitude, or its
    weights) and back, in its colours, framed once for the whole sweep."""
    half = max(frames // 2, 2)
    magnitudes = np.concatenate([np.linspace(0.0, 1.0, half + 1), np.linspace(1.0, 0.0, half + 1)[1:-1]])
    camera = render.fit_camera([result.neutral[result.mask], result.vertices[result.mask]],
                               width=PANEL_SIZE, height=PANEL_SIZE)
    grid = result.target.grid
    triangles = result.triangles()
    pictures = []
    for fraction in magnitudes:
        points = result.neutral + fraction * result.field_in_scan()
        pictures.append(_render(points, result.mask, grid, camera, triangles))
    render.save_gif(path, pictures, fps=fps)


def write_result_page(result, path, *, title: str | None = None) -> None:
    """The result's page for a browser (:func:`tpscore.showcase.viewer.write_result_html`)."""
    viewer.write_result_html(path, result, title=title)
