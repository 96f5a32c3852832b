import json

import numpy as np
import pytest

from tpscore.expression.action_units import ActionUnit, ActionUnitLibrary, ControlPoint, default_library
from tpscore.face.average_face import load_average_face


@pytest.fixture(scope="module")
def library():
    return default_library()


def test_shipped_library_has_the_eight_aus_with_regions(library):
    assert set(library.codes) == {"1", "2", "4", "12", "14", "15", "17", "20"}
    for code in ("1", "2", "4"):
        assert library[code].region == "upper"
    for code in ("12", "14", "15", "17", "20"):
        assert library[code].region == "lower"
    for au in library.action_units.values():
        kinds = {p.kind for p in au.control_points}
        assert "muscle" in kinds, au.code
        sides = [p.side for p in au.control_points]
        assert sides.count("left") == sides.count("right"), au.code  # mirrored pairs


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
    assert {a.label for a in library.parse("sadness")} == {"AU1", "AU4", "AU15"}
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
        code="9", name="Nose wrinkler", region="lower", muscle="levator labii superioris alaeque nasi",
        control_points=(ControlPoint(name="ala_left", kind="muscle", side="left", at={"Left nose peak": 1.0},
                                     offset_mm=(0.0, 3.0)),
                        ControlPoint(name="ala_right", kind="muscle", side="right", at={"Right nose peak": 1.0},
                                     offset_mm=(0.0, 3.0))))
    library.add(custom, replace=True)
    path = tmp_path / "aus.json"
    library.to_json(path)
    loaded = ActionUnitLibrary.from_json(path)
    assert loaded["9"].control_points == custom.control_points
    assert [a.label for a in loaded.parse("9R")] == ["AU9R"]


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
