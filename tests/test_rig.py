"""Rigs: the demo source's expressions transferred onto the demo target and written as
glTF 2.0 and USD, read back by pygltflib, usd-core and Blender; the ARKit names and
their halves; the source folders' layouts; bad input; the command line."""
from __future__ import annotations

import io as stdio
import json
import re
import struct

import numpy as np
import pytest
from PIL import Image

import tpscore
from tpscore.cli import main
from tpscore.cli.demo import write_demo_scans
from tpscore.rigging import ARKIT_NAMES, ARKIT_TABLE, Rig, plan_targets, source_scans, write_gltf
from tpscore.rigging.names import MIDLINE_BAND_MM, part_weights

pygltflib = pytest.importorskip("pygltflib")

# Two expressions keep the module to two transfers: a bilateral AU (which ARKit cuts in
# halves) and the surprise, which opens the mouth (whose triangles the rig must drop).
EXPRESSIONS = ["12", "surprise"]
# float32 metres hold a face's coordinates (< 0.2 m) to 1e-8 m; the displacements are
# asked to match the transfer's to 0.01 mm
POSITION_TOLERANCE_M = 1e-8
DISPLACEMENT_TOLERANCE_MM = 0.01


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    folder = tmp_path_factory.mktemp("demo") / "scans"
    write_demo_scans(folder)
    return folder


@pytest.fixture(scope="module")
def made(scans):
    messages = []
    made = tpscore.rig(None, scans, scans / "target_neutral.bnt", action_units=EXPRESSIONS,
                       progress=messages.append)
    return made, messages


@pytest.fixture(scope="module")
def glb(made, tmp_path_factory):
    path = tmp_path_factory.mktemp("rig") / "rig.glb"
    write_gltf(path, made[0], animations=True)
    return path


def _read(gltf, index) -> np.ndarray:
    """An accessor's data, as the reader gives it."""
    accessor = gltf.accessors[index]
    view = gltf.bufferViews[accessor.bufferView]
    dtype = {5126: np.float32, 5125: np.uint32}[accessor.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[accessor.type]
    blob = gltf.binary_blob()
    start = view.byteOffset + (accessor.byteOffset or 0)
    data = np.frombuffer(blob, dtype=dtype, count=accessor.count * width, offset=start)
    return data.reshape(accessor.count, width) if width > 1 else data


def test_the_rig_reads_the_shared_scans_once_and_transfers_each_expression(made, scans):
    rig, messages = made
    assert list(rig.results) == ["AU12", "surprise"]
    assert sum("read and resampled" in m for m in messages) == 1
    assert any(m.startswith("AU12 (1/2): transferred") for m in messages)
    assert any(m.startswith("surprise (2/2): measured the source's motion") for m in messages)
    # the transfer on the grids read once is the transfer of the files one by one
    alone = tpscore.transfer(scans / "source_neutral.bnt", scans / "source_au12.bnt", scans / "target_neutral.bnt",
                             "12")
    assert np.array_equal(alone.vertices, rig.results["AU12"].vertices, equal_nan=True)


def test_the_rig_keeps_no_triangle_any_expression_drops(made):
    rig, _ = made
    surprise = rig.results["surprise"]
    full = surprise.target.grid.triangles()
    assert len(surprise.triangles()) < len(full)  # the opened mouth is cut
    kept = {tuple(t) for t in rig.grid_index[rig.triangles]}
    for result in rig.results.values():
        assert kept <= {tuple(t) for t in result.triangles()}
    # and only those: every triangle that every result keeps is in the rig
    common = set.intersection(*({tuple(t) for t in r.triangles()} for r in rig.results.values()))
    assert kept == common


def test_the_glb_is_read_back_with_the_transfers_displacements(made, glb):
    rig, _ = made
    data = glb.read_bytes()
    magic, version, length = struct.unpack_from("<III", data)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    json_length, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_length % 4 == 0
    gltf = pygltflib.GLTF2().load(str(glb))
    assert gltf.asset.version == "2.0"
    assert len(gltf.meshes) == 1 and len(gltf.meshes[0].primitives) == 1
    mesh, primitive = gltf.meshes[0], gltf.meshes[0].primitives[0]
    assert mesh.extras["targetNames"] == ["AU12", "surprise"] == rig.target_names
    assert len(primitive.targets) == 2 and mesh.weights == [0.0, 0.0]

    positions = _read(gltf, primitive.attributes.POSITION)
    reference = rig.results["AU12"]
    neutral_mm = reference.neutral[reference.mask]
    assert np.abs(positions - neutral_mm / 1000).max() < POSITION_TOLERANCE_M
    indices = _read(gltf, primitive.indices).reshape(-1, 3)
    assert np.array_equal(indices, rig.triangles)
    assert indices.max() < len(positions)
    normals = _read(gltf, primitive.attributes.NORMAL)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    assert np.mean(normals[:, 2] > 0) > 0.9   # the face looks toward +z: the triangles run counter-clockwise
    uv = _read(gltf, primitive.attributes.TEXCOORD_0)
    assert np.allclose(uv, reference.uv[reference.mask], atol=1e-6)  # glTF's v runs down, as tpscore's

    for k, (name, result) in enumerate(rig.results.items()):
        moved = _read(gltf, primitive.targets[k]["POSITION"]) * 1000.0
        expected = (result.vertices - result.neutral)[result.mask]
        assert np.abs(moved - expected).max() < DISPLACEMENT_TOLERANCE_MM, name
        assert np.abs(expected).max() > 1.0  # the expression moves the face by millimetres

    for index in [primitive.attributes.POSITION] + [t["POSITION"] for t in primitive.targets]:
        accessor, values = gltf.accessors[index], _read(gltf, index)
        assert accessor.min == values.min(axis=0).tolist() and accessor.max == values.max(axis=0).tolist()
    for view in gltf.bufferViews:
        assert view.byteOffset % 4 == 0

    # the target's photograph, embedded and used as the base colour
    image = gltf.images[0]
    assert image.mimeType == "image/png" and image.uri is None
    view = gltf.bufferViews[image.bufferView]
    png = gltf.binary_blob()[view.byteOffset:view.byteOffset + view.byteLength]
    assert np.array_equal(np.asarray(Image.open(stdio.BytesIO(png)).convert("RGB")), reference.image)
    material = gltf.materials[primitive.material]
    assert material.pbrMetallicRoughness.baseColorTexture.index == 0

    # one animation per expression: its target 0 -> 1 -> 0 over a second
    assert [a.name for a in gltf.animations] == ["AU12", "surprise"]
    for k, animation in enumerate(gltf.animations):
        sampler = animation.samplers[0]
        assert sampler.interpolation == "LINEAR" and animation.channels[0].target.path == "weights"
        assert _read(gltf, sampler.input).tolist() == [0.0, 0.5, 1.0]
        weights = _read(gltf, sampler.output).reshape(3, 2)
        assert weights.tolist() == [[0, 0], [float(k == 0), float(k == 1)], [0, 0]]


def test_a_gltf_file_holds_the_same_rig_inline(made, glb, tmp_path):
    rig, _ = made
    path = write_gltf(tmp_path / "rig.gltf", rig, normals=False)
    text = json.loads(path.read_text())
    assert text["buffers"][0]["uri"].startswith("data:application/octet-stream;base64,")
    inline, binary = pygltflib.GLTF2().load(str(path)), pygltflib.GLTF2().load(str(glb))
    inline.convert_buffers(pygltflib.BufferFormat.BINARYBLOB)
    assert "NORMAL" not in text["meshes"][0]["primitives"][0]["attributes"]
    position = inline.meshes[0].primitives[0].attributes.POSITION
    assert np.array_equal(_read(inline, position), _read(binary, binary.meshes[0].primitives[0].attributes.POSITION))


def test_arkit_names_cut_a_bilateral_au_into_halves_that_add_up(made):
    rig, _ = made
    arkit = Rig.from_results(rig.results, names="arkit")
    assert arkit.target_names == ["mouthSmileLeft", "mouthSmileRight", "surprise"]
    left, right = arkit.displacement("mouthSmileLeft"), arkit.displacement("mouthSmileRight")
    whole = rig.displacement("AU12")
    assert np.allclose(left + right, whole, rtol=0, atol=1e-12)
    assert np.array_equal(arkit.displacement("surprise"), rig.displacement("surprise"))
    # each half is the whole on its own side (the subject's left is +x) and nothing on the other
    x = rig.results["AU12"].neutral_normalised[rig.results["AU12"].mask][:, 0]
    far = np.abs(x) > MIDLINE_BAND_MM / 2
    assert np.array_equal(left[far & (x > 0)], whole[far & (x > 0)]) and not left[far & (x < 0)].any()
    assert np.array_equal(right[far & (x < 0)], whole[far & (x < 0)]) and not right[far & (x > 0)].any()
    # the smile moves both mouth corners: each half has millimetres of it
    assert np.linalg.norm(left, axis=1).max() > 1.0 and np.linalg.norm(right, axis=1).max() > 1.0


def test_the_arkit_table_and_its_rules():
    for code, (shape, rank) in ARKIT_TABLE.items():
        for name in ([shape] if isinstance(shape, str) else shape):
            assert name in ARKIT_NAMES, (code, name)
    assert len(set(ARKIT_NAMES)) == 52
    planned = plan_targets(["AU12", "AU12L", "AU1", "AU1L", "AU26", "AU27", "AU28", "AU25", "AU4+AU7", "sadness"],
                           "arkit")
    assert [(t.name, t.expression, t.part) for t in planned] == [
        # the one-sided scan of the left side takes its name; the bilateral AU12 then keeps its own, whole
        ("AU12", "AU12", None), ("mouthSmileLeft", "AU12L", None),
        ("browInnerUp", "AU1", None), ("AU1L", "AU1L", None),   # browInnerUp has no sides
        ("jawOpen", "AU26", None), ("AU27", "AU27", None),      # AU26 is the closer match
        ("mouthRollUpper", "AU28", "upper"), ("mouthRollLower", "AU28", "lower"),
        ("AU25", "AU25", None), ("AU4+AU7", "AU4+AU7", None), ("sadness", "sadness", None)]
    assert [t.name for t in plan_targets(["AU27", "AU43"], "arkit")] == [
        "jawOpen", "eyeBlinkLeft", "eyeBlinkRight"]
    assert [(t.name, t.part) for t in plan_targets(["AU12", "AU4"])] == [("AU12", None), ("AU4", None)]
    # the lips' halves add up too
    points = np.column_stack([np.zeros(9), np.linspace(-40, 0, 9), np.zeros(9)])
    landmarks = np.full((22, 3), np.nan)
    landmarks[[15, 16], 1] = -20.0  # the mouth corners
    landmarks[[15, 16], 0], landmarks[[15, 16], 2] = (-25.0, 25.0), 0.0
    upper, lower = part_weights("upper", points, landmarks), part_weights("lower", points, landmarks)
    assert np.allclose(upper + lower, 1.0) and upper[0] == 0.0 and upper[-1] == 1.0


def test_source_folders_in_either_layout(tmp_path):
    bosphorus = tmp_path / "bs007"
    bosphorus.mkdir()
    for code in ("N_N_0", "LFAU_12_0", "UFAU_4_0", "E_SADNESS_0", "YR_R90_0", "CAU_A22A25_0"):
        (bosphorus / f"bs007_{code}.bnt").touch()
    found = source_scans(bosphorus)
    assert found.neutral.endswith("bs007_N_N_0.bnt")
    assert list(found) == ["22+25", "sadness", "12", "4"]  # by file name; the pose is left out
    flat = tmp_path / "flat"
    flat.mkdir()
    for stem in ("source_neutral", "source_au12", "source_AU12L", "source_sadness", "target_neutral"):
        (flat / f"{stem}.bnt").touch()
    found = source_scans(flat)
    assert found.neutral.endswith("source_neutral.bnt") and sorted(found) == ["12", "12L", "sadness"]
    (bosphorus / "bs008_N_N_0.bnt").touch()
    with pytest.raises(ValueError, match="expressions: .* 2 subjects"):
        source_scans(bosphorus)
    with pytest.raises(ValueError, match="give one subject's folder"):
        source_scans(tmp_path)


@pytest.mark.parametrize("call, word", [
    pytest.param(lambda s, t: tpscore.rig(None, s, s / "target_neutral.bnt", names="blender"), "names",
                 id="unknown-names"),
    pytest.param(lambda s, t: tpscore.rig(None, t / "missing", s / "target_neutral.bnt"),
                 "expressions: .*folder not found", id="missing-folder"),
    pytest.param(lambda s, t: tpscore.rig(None, t, s / "target_neutral.bnt"), "expressions: no expressive scan",
                 id="no-expressions"),
    pytest.param(lambda s, t: tpscore.rig(None, s, s / "target_neutral.bnt", action_units=["27"]),
                 "action_units: no source scan shows AU27", id="absent-au"),
])
def test_bad_input_names_the_argument(scans, tmp_path, call, word):
    with pytest.raises(ValueError, match=word):
        call(scans, tmp_path)


def test_the_function_and_the_package_are_both_at_hand():
    import tpscore.rigging.names as names

    assert tpscore.rig is tpscore.rigging.build.rig and tpscore.rigging.gltf.write_gltf is tpscore.write_gltf
    assert names.ARKIT_NAMES is ARKIT_NAMES


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_usd_holds_a_blend_shape_per_morph_target(made, tmp_path, suffix):
    pytest.importorskip("pxr", reason="USD output needs usd-core (the usd extra)")
    from pxr import Usd, UsdGeom, UsdSkel, Vt
    from tpscore.rigging.usd import write_usd

    rig = Rig.from_results(made[0].results, names="arkit")
    path = write_usd(tmp_path / f"rig{suffix}", rig, animations=True)
    assert (tmp_path / "rig_texture.png").is_file()
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    face = stage.GetPrimAtPath("/Rig/Face")
    points = np.array(face.GetAttribute("points").Get())
    assert np.abs(points - rig.vertices / 1000).max() < POSITION_TOLERANCE_M
    binding = UsdSkel.BindingAPI(face)
    assert list(binding.GetBlendShapesAttr().Get()) == rig.target_names
    shapes = UsdSkel.BlendShapeQuery(binding)
    assert shapes.GetNumBlendShapes() == len(rig.targets)
    for k, name in enumerate(rig.target_names):
        # UsdSkel's own evaluation of the shape at weight 1
        weights = shapes.ComputeSubShapeWeights(Vt.FloatArray([float(j == k) for j in range(len(rig.targets))]))
        posed = face.GetAttribute("points").Get()
        assert shapes.ComputeDeformedPoints(*weights, shapes.ComputeBlendShapePointIndices(),
                                            shapes.ComputeSubShapePointOffsets(), posed)
        moved = (np.array(posed) - points) * 1000
        assert np.abs(moved - rig.displacement(name)).max() < DISPLACEMENT_TOLERANCE_MM, name
    weights = UsdSkel.Animation(stage.GetPrimAtPath("/Rig/Skeleton/Weights")).GetBlendShapeWeightsAttr()
    assert list(weights.Get(0.0)) == [0.0, 0.0, 0.0] and list(weights.Get(12.0)) == [1.0, 1.0, 0.0]
    assert list(weights.Get(36.0)) == [0.0, 0.0, 1.0]

@pytest.mark.parametrize("arguments, word", [
    pytest.param(lambda s, t: ["--names", "blender"], "--names", id="unknown-names"),
    pytest.param(lambda s, t: ["--source-dir", str(t / "missing")], "--source-dir", id="missing-folder"),
    pytest.param(lambda s, t: ["--source-dir", str(t)], "--source-dir: no expressive scan", id="no-expressions"),
    pytest.param(lambda s, t: ["--au", "27"], "--au: no source scan shows AU27", id="absent-au"),
    pytest.param(lambda s, t: ["--out", str(t / "rig.fbx")], "--out", id="unknown-format"),
])
def test_the_command_line_names_the_option(scans, tmp_path, capsys, arguments, word):
    given = dict(zip(*[iter(["--source-dir", str(scans), "--target", str(scans / "target_neutral.bnt"),
                             "--out", str(tmp_path / "rig.glb")])] * 2))
    extra = arguments(scans, tmp_path)
    given.update(zip(extra[::2], extra[1::2]))
    try:
        code = main(["rig", *[item for pair in given.items() for item in pair], "--quiet"])
    except SystemExit as stopped:  # argparse's own refusals
        code = stopped.code
    err = capsys.readouterr().err
    assert code == 2 and word in err and err.count("\n") == 1, err


def test_tpscore_rig_writes_an_arkit_glb(scans, tmp_path, capsys):
    out = tmp_path / "rig.glb"
    code = main(["rig", "--source-dir", str(scans), "--target", str(scans / "target_neutral.bnt"), "--out", str(out),
                 "--au", "4", "--names", "arkit", "--animations", "--grid", "80x80", "--html", str(tmp_path / "rig.html")])
    assert code == 0
    assert '"targets": ["browDownLeft", "browDownRight"]' in (tmp_path / "rig.html").read_text()
    printed = capsys.readouterr().out
    assert "AU4 (1/1): transferred" in printed and f"wrote {out}" in printed
    gltf = pygltflib.GLTF2().load(str(out))
    assert gltf.meshes[0].extras["targetNames"] == ["browDownLeft", "browDownRight"]
    assert [a.name for a in gltf.animations] == ["AU4"]
    assert gltf.accessors[gltf.meshes[0].primitives[0].attributes.POSITION].count < 80 * 80


# Blender's importer turns glTF's +y up into its own +z up: (x, y, z) -> (x, -z, y).
_BLENDER_SCRIPT = """
import sys
import bpy
import numpy as np

glb, out = sys.argv[1], sys.argv[2]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=glb)
faces = [o for o in bpy.data.objects if o.type == "MESH"]
face = faces[0]
keys = face.data.shape_keys.key_blocks

def coordinates(points):
    flat = np.empty(len(points) * 3)
    points.foreach_get("co", flat)
    return flat.reshape(-1, 3)

arrays = {f"key{k}": coordinates(block.data) for k, block in enumerate(keys)}
keys[1].value = 1.0   # the first morph target at weight 1, as an animator sets it
evaluated = face.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
arrays["moved"] = coordinates(evaluated.vertices)
arrays["world"] = np.array(face.matrix_world)
np.savez(out, names=np.array([block.name for block in keys]), meshes=len(faces),
         images=len(bpy.data.images), **arrays)
"""


def test_blender_opens_the_rig_with_a_shape_key_per_morph_target(made, glb, blender, tmp_path):
    from headless_blender import run_blender
    from scipy.spatial import cKDTree

    rig, _ = made
    arkit = tmp_path / "arkit.glb"
    write_gltf(arkit, Rig.from_results(rig.results, names="arkit"))
    run_blender(blender, _BLENDER_SCRIPT, arkit, tmp_path / "blender.npz")
    with np.load(tmp_path / "blender.npz") as seen:
        seen = dict(seen)
    names = ["mouthSmileLeft", "mouthSmileRight", "surprise"]
    assert seen["names"].tolist() == ["Basis", *names]
    assert int(seen["meshes"]) == 1 and int(seen["images"]) == 1
    assert np.allclose(seen["world"], np.eye(4))

    def in_blender(points_mm):
        metres = np.asarray(points_mm) / 1000.0
        return np.column_stack([metres[:, 0], -metres[:, 2], metres[:, 1]])

    # the importer may order the vertices its own way: match them by position
    basis = seen["key0"]
    distance, order = cKDTree(basis).query(in_blender(rig.vertices))
    assert len(basis) == len(rig.vertices) and distance.max() < 1e-6 and len(set(order)) == len(order)
    arkit_rig = Rig.from_results(rig.results, names="arkit")
    for k, name in enumerate(names, 1):
        moved = (seen[f"key{k}"] - basis)[order]
        expected = in_blender(arkit_rig.displacement(name))
        assert np.abs(moved - expected).max() * 1000 < DISPLACEMENT_TOLERANCE_MM, name
    # the first key at 1 moves the mesh as the transfer moves the target's left mouth corner
    moved = (seen["moved"] - basis)[order]
    assert np.abs(moved - in_blender(arkit_rig.displacement("mouthSmileLeft"))).max() * 1000 < \
        DISPLACEMENT_TOLERANCE_MM


def test_the_rig_page_has_a_slider_per_target_that_moves_the_face(made, tmp_path, chromium):
    pytest.importorskip("websocket", reason="the browser test talks to Chromium with websocket-client")
    from headless_browser import Browser

    made, _ = made
    path = tmp_path / "rig.html"
    made.write_html(path)
    text = path.read_text()
    assert "data:image/png;base64," in text and not re.search(r"https?://", text)
    browser = Browser(chromium)
    try:
        browser.open(path)
        browser.wait_for("window.tpscoreViewer && window.tpscoreViewer.ready")
        sliders = browser.evaluate("document.querySelectorAll('#targets input[type=range]').length")
        assert sliders == len(made.targets)
        labels = browser.evaluate("Array.from(document.querySelectorAll('#targets label')).map(l => l.textContent)")
        assert labels == made.target_names
        neutral = browser.screenshot("#face")
        frames = browser.evaluate("window.tpscoreViewer.frames")
        weights = [0.0] * len(made.targets)
        weights[made.target_names.index("surprise")] = 1.0
        browser.evaluate(f"window.tpscoreViewer.setWeights({weights})")
        browser.wait_for(f"window.tpscoreViewer.frames > {frames}")
        opened = browser.screenshot("#face")
        changed = (np.abs(opened.astype(int) - neutral.astype(int)).sum(axis=2) > 30)
        assert changed.mean() > 0.01  # the surprise's slider moved the face
        assert browser.errors() == []
    finally:
        browser.close()
