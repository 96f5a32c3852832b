import json

import numpy as np
import pytest

from tpscore.expression.action_units import ActionUnit, ActionUnitLibrary, ControlPoint, default_library
from tpscore.face.average_face import load_average_face
from tpscore.face.landmarks import AnchoredPoint, landmark_index
from tpscore.face.regions import Region


@pytest.fixture(scope="module")
def library():
    return default_library()


BOSPHORUS_AUS = {"1", "2", "4", "5", "6", "7", "9", "10", "12", "14", "15", "16", "17", "18", "20", "22", "23",
                 "24", "25", "26", "27", "28", "34", "43", "44"}


def test_shipped_library_has_every_bosphorus_au_with_its_region(library):
    assert set(library.codes) == BOSPHORUS_AUS
    for code in ("1", "2", "4"):
        assert library[code].region == "upper"
    for code in ("12", "14", "15", "18", "20", "22", "23", "24", "25", "26", "27", "28", "34"):
        assert library[code].region == "lower"
    assert library["16"].region == library["17"].region == "chin_lower_lip"
    for code in ("5", "7", "43", "44"):
        assert library[code].region == "eyes"
    assert library["6"].region == "eyes_cheeks"
    assert library["9"].region == library["10"].region == "nose_upper_lip"
    for au in library.action_units.values():
        assert au.name and au.muscle, au.code  # the FACS name and its muscles
        kinds = {p.kind for p in au.control_points}
        assert "muscle" in kinds, au.code
        sides = [p.side for p in au.control_points]
        assert sides.count("left") == sides.count("right"), au.code  # mirrored pairs


def test_named_regions_cover_where_their_muscles_act(library):
    landmarks = load_average_face().landmarks
    eyes = library.regions["eyes"]
    lid = library["43"].positions_xy(landmarks)
    assert (eyes.weight(np.column_stack([lid, np.zeros(len(lid))]), landmarks) == 1).all()
    chin = landmarks[21:22]
    assert eyes.weight(chin, landmarks)[0] == 0
    nose = library.regions["nose_upper_lip"]
    inside = landmarks[[13, 16, 10, 11]]  # nose tip, upper lip, the nose's saddles
    assert (nose.weight(inside, landmarks) == 1).all()
    assert nose.weight(landmarks[[20, 21]], landmarks).max() < 1  # lower lip and chin: outside or on the edge
    # the chin's region holds the lower lip and the chin, not the upper lip above the
    # lips' line (a chin raiser's smooth field would push it up): 0 from 8 mm above it
    chin_region = library.regions["chin_lower_lip"]
    at = [landmark_index(name) for name in ("Upper lip outer middle", "Upper lip inner middle",
                                            "Lower lip inner middle", "Lower lip outer middle", "Chin middle")]
    assert (chin_region.weight(landmarks[at[3:]], landmarks) == 1).all()  # the lower lip, the chin
    lips_line = landmarks[at[1:3]].mean(axis=0)
    above = lips_line + [[0.0, 2.0, 0.0], [0.0, 8.5, 0.0]]
    assert 0 < chin_region.weight(above[:1], landmarks)[0] < 1 and chin_region.weight(above[1:], landmarks)[0] == 0
    assert chin_region.weight(landmarks[at[:1]], landmarks)[0] < 0.5  # the upper lip's outer middle
    for code in ("16", "17"):  # the published method's control points lie in it
        xy = library[code].positions_xy(landmarks)
        assert (chin_region.weight(np.column_stack([xy, np.zeros(len(xy))]), landmarks) > 0.5).all(), code
    # weights fall smoothly: a point just outside a polygon has a weight between 0 and 1
    corner = eyes.corners(landmarks)[0]
    outside = corner.mean(axis=0) + 1.02 * (corner[0] - corner.mean(axis=0))
    assert 0 < eyes.weight(np.append(outside, 0.0)[None], landmarks)[0] <= 1


def test_a_region_knows_the_half_of_the_face_it_lies_in(library):
    landmarks = load_average_face().landmarks
    assert library.regions["chin_lower_lip"].half(landmarks, 10.0) == "lower"
    for name in ("eyes", "eyes_cheeks", "nose_upper_lip"):  # across the eye line
        assert library.regions[name].half(landmarks, 10.0) is None, name
    forehead = Region("forehead", ((AnchoredPoint("a", "centre", {"Outer left eyebrow": 1.0}, (0.0, 20.0)),
                                    AnchoredPoint("b", "centre", {"Outer right eyebrow": 1.0}, (0.0, 20.0)),
                                    AnchoredPoint("c", "centre", {"Inner right eyebrow": 1.0}, (0.0, 50.0))),),
                      margin_mm=5.0)
    assert forehead.half(landmarks) == "upper"
    # a soft edge that reaches the eye line leaves it in neither half
    assert Region("wide", forehead.polygons, margin_mm=40.0).half(landmarks) is None
    with pytest.raises(ValueError, match="seam_mm"):
        forehead.half(landmarks, -1.0)


def test_emotions_follow_table_3_3(library):
    expected = {"surprise": {"1", "2", "5", "26"}, "fear": {"1", "2", "4", "5", "20", "27"},
                "happiness": {"6", "12"}, "sadness": {"1", "4", "15"}, "disgust": {"9", "17"},
                "anger": {"4", "5", "7", "23", "25"}}
    for name, codes in expected.items():
        assert set(library.emotions[name]) == codes, name


def test_control_points_sit_where_the_anatomy_says(library):
    landmarks = load_average_face().landmarks
    brow = library["1"].positions_xy(landmarks)
    eye_y = landmarks[[6, 7, 8, 9], 1].mean()
    assert (brow[:, 1] > eye_y).all()  # brow AU points above the eyes
    smile = library["12"]
    xy = smile.positions_xy(landmarks)
    sides = np.array([p.side for p in smile.control_points])
    assert (xy[sides == "left", 0] > 0).all() and (xy[sides == "right", 0] < 0).all()
    assert (xy[:, 1] < eye_y).all()


def test_parse_specs(library):
    assert [a.label for a in library.parse("12")] == ["AU12"]
    assert [a.label for a in library.parse("AU12L")] == ["AU12L"]
    assert [a.label for a in library.parse("1,4,15")] == ["AU1", "AU4", "AU15"]
    acts = library.parse("12:0.5 + 12:0.25")
    assert len(acts) == 1 and acts[0].weight == pytest.approx(0.75)
    sadness = library.parse("sadness")
    assert [a.label for a in sadness] == ["sadness"] and sadness[0].whole and sadness[0].bilateral
    assert {a.label for a in library.recipe(sadness[0])} == {"AU1", "AU4", "AU15"}
    whole = library.parse("all:0.5")
    assert [a.label for a in whole] == ["all"] and whole[0].weight == 0.5 and not whole[0].bilateral
    with pytest.raises(ValueError, match="no recipe"):
        library.recipe(whole[0])
    with pytest.raises(ValueError, match="whole expression"):
        library.parse("happiness,12")
    assert [a.label for a in library.parse("43")] == ["AU43"]
    assert library.parse({"20": 0.3})[0].weight == pytest.approx(0.3)
    with pytest.raises(ValueError, match="unknown action unit '99'"):
        library.parse("99")
    with pytest.raises(ValueError, match="no action unit"):
        library.parse("")
    with pytest.raises(ValueError, match="bad weight"):
        library.parse("12:x")


def test_one_sided_weights(library):
    au = library["17"]  # has centre points
    w = au.side_weights("L")
    sides = [p.side for p in au.control_points]
    for weight, side in zip(w, sides):
        assert weight == {"left": 1.0, "right": 0.0, "centre": 0.5}[side]
    assert (au.side_weights(None) == 1).all()


def test_user_defined_au_round_trips_through_json(tmp_path, library):
    custom = ActionUnit(
        code="11", name="Nasolabial deepener", region="lower", muscle="zygomaticus minor",
        control_points=(ControlPoint(name="ala_left", kind="muscle", side="left", at={"Left nose peak": 1.0},
                                     offset_mm=(0.0, 3.0)),
                        ControlPoint(name="ala_right", kind="muscle", side="right", at={"Right nose peak": 1.0},
                                     offset_mm=(0.0, 3.0))))
    library.add(custom, replace=True)
    path = tmp_path / "aus.json"
    library.to_json(path)
    loaded = ActionUnitLibrary.from_json(path)
    assert loaded["11"].control_points == custom.control_points
    assert [a.label for a in loaded.parse("11R")] == ["AU11R"]
    assert loaded.regions.keys() == library.regions.keys()
    assert loaded["43"].region == "eyes"


@pytest.mark.parametrize("bad, message", [
    ({"name": "p", "kind": "bone", "side": "left", "at": {"Nose tip": 1}}, "kind must be"),
    ({"name": "p", "kind": "muscle", "side": "up", "at": {"Nose tip": 1}}, "side must be"),
    ({"name": "p", "kind": "muscle", "side": "left", "at": {"Nose top": 1}}, "unknown landmark name"),
    ({"name": "p", "kind": "muscle", "side": "left", "at": {"Nose tip": -1}}, "must be > 0"),
])
def test_bad_control_points_are_refused(bad, message):
    entry = {"code": "50", "name": "x", "region": "lower", "control_points": [bad]}
    with pytest.raises(ValueError, match=message):
        ActionUnitLibrary.from_dict({"action_units": [entry]})


def test_unreadable_library_names_the_file(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text("{ not json")
    with pytest.raises(ValueError, match="broken.json"):
        ActionUnitLibrary.from_json(path)
    path.write_text(json.dumps({"emotions": {}}))
    with pytest.raises(ValueError, match="action_units"):
        ActionUnitLibrary.from_json(path)


def test_the_shared_shipped_library_is_read_only_and_pickles_as_itself():
    import copy
    import pickle

    from tpscore.expression.action_units import shipped_library

    shared = shipped_library()
    assert shared.codes == default_library().codes
    with pytest.raises(ValueError, match="read-only"):
        shared.add_emotion("smirk", {"12L": 1.0})
    assert "smirk" not in shipped_library().emotions
    assert pickle.loads(pickle.dumps(shared)) is shared
    assert copy.deepcopy(shared) is shared
    own = default_library()
    own.add_emotion("smirk", {"12L": 1.0})  # a caller's own library changes freely
    assert "smirk" in own.emotions and "smirk" not in shared.emotions
