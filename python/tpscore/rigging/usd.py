"""The rig as USD (``.usda`` text, ``.usdc`` or ``.usd`` binary): a UsdSkel blend-shape
rig, which USD's own tools, Omniverse, Houdini, Maya and Blender open.

The stage, in metres with +y up like the glTF: a SkelRoot ``/Rig`` holding the face
mesh (points, triangles, u,v as ``primvars:st``, a UsdPreviewSurface material
reading the target's photograph, written beside the file as ``<stem>_texture.png``),
one BlendShape prim under it per morph target (its offsets at every vertex), and a
Skeleton of one joint whose SkelAnimation holds the shapes' weights: 0 by default, and
with ``animations`` each expression's shapes taken 0 -> 1 -> 0 over a second of its
own, one expression after the other.

Needs usd-core (``pip install tpscore[usd]``); without it :func:`write_usd` says so.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from .._files import atomic_write
from .._validation import as_path
from ..face.io import write_png
from .build import Rig
from .gltf import ANIMATION_SECONDS, METRES_PER_MM

__all__ = ["write_usd", "require_usd", "USD_SUFFIXES"]

USD_SUFFIXES = (".usda", ".usdc", ".usd")
# Frames per second of the animation's time codes.
_FPS = 24


def require_usd() -> None:
    """Nothing when usd-core (the ``pxr`` package) is installed; else a ValueError that
    says how to get it (the command line checks before it runs the transfers)."""
    try:
        from pxr import Usd  # noqa: F401
    except ImportError:
        raise ValueError("writing USD needs the usd-core package: pip install 'tpscore[usd]' "
                         "(or write the rig as .glb)") from None


def write_usd(path, rig: Rig, *, animations: bool = False) -> Path:
    """Write a rig as a UsdSkel blend-shape rig (see the module's text), atomically; with
    a texture, ``<stem>_texture.png`` is written beside it first.

    Raises
    ------
    ValueError
        `path` does not end in .usda, .usdc or .usd, its folder does not exist, `rig` is
        not a Rig, or usd-core is not installed.
    """
    target = Path(as_path(path, "path"))
    if target.suffix.lower() not in USD_SUFFIXES:
        raise ValueError(f"path: {str(target)!r}: a USD file ends in {', '.join(USD_SUFFIXES)}")
    if not isinstance(rig, Rig):
        raise ValueError(f"rig must be a Rig (made by tpscore.rig), got {type(rig).__name__}")
    if not target.resolve().parent.is_dir():
        raise ValueError(f"cannot write {str(target)!r}: the folder {str(target.parent)!r} does not exist")
    require_usd()
    texture = None
    if rig.image is not None:
        texture = target.with_name(f"{target.stem}_texture.png")
        write_png(texture, rig.image)
    stage = _stage(rig, texture.name if texture is not None else None, animations)
    layer = stage.GetRootLayer()
    if target.suffix.lower() == ".usda":
        data = layer.ExportToString().encode("utf-8")
    else:
        # the binary format is only written to a file: export to a private one, then
        # write its bytes in place (the texture's path in it is relative, so it moves)
        with tempfile.TemporaryDirectory(prefix="tpscore-usd-") as folder:
            scratch = os.path.join(folder, "rig" + target.suffix.lower())
            if not layer.Export(scratch):
                raise OSError(f"cannot write {str(target)!r}: USD could not export the stage")
            data = Path(scratch).read_bytes()
    atomic_write(target, data, "path")
    return target


def _stage(rig: Rig, texture: str | None, animations: bool):
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdSkel.Root.Define(stage, "/Rig")
    stage.SetDefaultPrim(root.GetPrim())

    points = (rig.vertices * METRES_PER_MM).astype(np.float32)
    mesh = UsdGeom.Mesh.Define(stage, "/Rig/Face")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(rig.triangles), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(rig.triangles.astype(np.int32).reshape(-1)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # a scan's triangles, not a subdivision cage
    mesh.CreateDoubleSidedAttr(True)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, points.min(axis=0))),
                                         Gf.Vec3f(*map(float, points.max(axis=0)))]))
    # USD's t runs up the image, tpscore's v down
    st = np.column_stack([rig.uv[:, 0], 1.0 - rig.uv[:, 1]]).astype(np.float32)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                            UsdGeom.Tokens.vertex).Set(Vt.Vec2fArray.FromNumpy(st))
    _material(stage, mesh, texture)

    skeleton = UsdSkel.Skeleton.Define(stage, "/Rig/Skeleton")
    skeleton.CreateJointsAttr(["root"])  # blend shapes are driven through a skeleton; one still joint
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    names = rig.target_names
    animation = UsdSkel.Animation.Define(stage, "/Rig/Skeleton/Weights")
    animation.CreateBlendShapesAttr(names)
    weights = animation.CreateBlendShapeWeightsAttr(Vt.FloatArray(len(names), 0.0))
    if animations:
        _keys(stage, weights, rig)
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets([animation.GetPath()])

    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
    binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    binding.CreateBlendShapesAttr(names)
    shapes, used = [], set()
    for target in rig.targets:
        # a prim's name is an identifier ("AU4+AU7" is not); the shape keeps its own name
        # in skel:blendShapes
        prim_name = Tf.MakeValidIdentifier(target.name)
        while prim_name in used:
            prim_name += "_"
        used.add(prim_name)
        shape = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(prim_name))
        shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy((target.displacement * METRES_PER_MM).astype(np.float32)))
        shapes.append(shape.GetPath())
    binding.CreateBlendShapeTargetsRel().SetTargets(shapes)
    return stage


def _material(stage, mesh, texture: str | None) -> None:
    from pxr import Sdf, UsdShade

    material = UsdShade.Material.Define(stage, "/Rig/Materials/Skin")
    surface = UsdShade.Shader.Define(stage, "/Rig/Materials/Skin/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.8)
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    colour = surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
    if texture is None:
        colour.Set((0.78, 0.70, 0.62))  # clay, as the glTF's face without a photograph
    else:
        reader = UsdShade.Shader.Define(stage, "/Rig/Materials/Skin/St")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
        image = UsdShade.Shader.Define(stage, "/Rig/Materials/Skin/Photograph")
        image.CreateIdAttr("UsdUVTexture")
        image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(f"./{texture}")
        image.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
        image.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
        image.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
        colour.ConnectToSource(image.ConnectableAPI(), "rgb")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)


def _keys(stage, weights, rig: Rig) -> None:
    """Each expression's shapes 0 -> 1 -> 0 over its own second, one after the other."""
    from pxr import Vt

    stage.SetTimeCodesPerSecond(_FPS)
    frames = ANIMATION_SECONDS * _FPS
    zero = np.zeros(len(rig.targets), dtype=np.float32)
    for k, expression in enumerate(rig.results):
        start = k * frames
        peak = np.array([t.expression == expression for t in rig.targets], dtype=np.float32)
        for time, value in ((start, zero), (start + frames / 2, peak), (start + frames, zero)):
            weights.Set(Vt.FloatArray.FromNumpy(value), time)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(len(rig.results) * frames)
