"""The result page in a real headless browser, and the page's text without one."""
import re

import numpy as np
import pytest

from tpscore import load_scan, transfer
from tpscore.showcase import demo_faces, viewer


@pytest.fixture(scope="module")
def smile_page(tmp_path_factory):
    """A page of AU12 carried from one demo person to another, and the result."""
    folder = tmp_path_factory.mktemp("page")
    scans = [demo_faces.make_demo_scan(0, None, seed=1), demo_faces.make_demo_scan(0, {"12": 1.0}, seed=2),
             demo_faces.make_demo_scan(1, None, seed=3)]
    grids = [load_scan(scan.write(folder, name)) for scan, name in zip(scans, ("a", "b", "c"))]
    result = transfer(*grids, "12", 0.8)
    path = folder / "smile.html"
    viewer.write_result_html(path, result)
    return path, result


@pytest.fixture(scope="module")
def browser(chromium):
    websocket = pytest.importorskip("websocket", reason="the browser test talks to Chromium with websocket-client")
    del websocket
    from headless_browser import Browser

    session = Browser(chromium)
    yield session
    session.close()


def _open(browser, path):
    browser.events.clear()
    browser.open(path)
    browser.wait_for("window.tpscoreViewer && window.tpscoreViewer.ready")


def test_page_is_self_contained(smile_page):
    path, result = smile_page
    text = path.read_text()
    # nothing is fetched: no address of any server, no external script or style
    assert not re.search(r"https?://", text)
    assert "<script src" not in text and "<link" not in text
    assert "data:image/png;base64," in text
    # the slider starts at the transfer's magnitude and ends at 1
    assert 'max="1" step="0.01" value="0.80"' in text
    # one page of about a megabyte or two: the face, the field and the photograph
    assert 0.3e6 < len(text) < 4e6


def test_page_loads_without_errors_and_shows_the_face(browser, smile_page):
    path, _ = smile_page
    _open(browser, path)
    picture = browser.screenshot("#face")
    assert browser.errors() == []
    # the canvas is not blank: much of it is face (not the white background), in
    # many colours, and the face is skin: redder than it is blue
    face = (picture < 245).any(axis=2)
    assert 0.2 < face.mean() < 0.9
    skin = picture[face].astype(float)
    assert skin.std(axis=0).mean() > 10
    assert (skin[:, 0] > skin[:, 2]).mean() > 0.9
    assert browser.evaluate("document.getElementById('error').textContent") == ""


def test_moving_the_slider_moves_the_mouth(browser, smile_page):
    path, _ = smile_page
    _open(browser, path)
    at_start = browser.screenshot("#face")
    slider = browser.rect("#magnitude")
    frames = browser.evaluate("window.tpscoreViewer.frames")
    # a click at the slider's left end takes the magnitude to 0: the neutral face
    browser.click(slider["x"] + 2, slider["y"] + slider["height"] / 2)
    browser.wait_for(f"window.tpscoreViewer.frames > {frames}")
    assert browser.evaluate("window.tpscoreViewer.magnitude") < 0.05
    neutral = browser.screenshot("#face")
    difference = np.abs(at_start.astype(int) - neutral.astype(int)).sum(axis=2)
    changed = difference > 30
    assert changed.mean() > 0.01
    # a smile moves the lower face: what changed lies mostly below the nose, i.e. in
    # the lower part of the canvas (the face is drawn upright, centred)
    rows = np.nonzero(changed)[0]
    assert np.mean(rows > 0.55 * changed.shape[0]) > 0.6
    # back at the right end of the slider, the picture is the smile at magnitude 1,
    # which differs from the start (0.8) far less than from neutral
    frames = browser.evaluate("window.tpscoreViewer.frames")
    browser.click(slider["x"] + slider["width"] - 2, slider["y"] + slider["height"] / 2)
    browser.wait_for(f"window.tpscoreViewer.frames > {frames}")
    assert browser.evaluate("window.tpscoreViewer.magnitude") > 0.95
    full = browser.screenshot("#face")
    assert (np.abs(full.astype(int) - at_start.astype(int)).sum(axis=2) > 30).mean() < changed.mean()
    assert browser.errors() == []


def test_dragging_turns_the_face(browser, smile_page):
    path, _ = smile_page
    _open(browser, path)
    before = browser.screenshot("#face")
    canvas = browser.rect("#face")
    centre = (canvas["x"] + canvas["width"] / 2, canvas["y"] + canvas["height"] / 2)
    frames = browser.evaluate("window.tpscoreViewer.frames")
    browser.drag(centre, (centre[0] + 120, centre[1]))
    browser.wait_for(f"window.tpscoreViewer.frames > {frames}")
    after = browser.screenshot("#face")
    assert (np.abs(after.astype(int) - before.astype(int)).sum(axis=2) > 30).mean() > 0.05
    assert browser.errors() == []


def test_page_without_a_photograph_is_clay(tmp_path):
    # a plane of 3 x 3 vertices bulging forward with the slider
    x, y = np.meshgrid(np.linspace(-50, 50, 3), np.linspace(-50, 50, 3))
    neutral = np.column_stack([x.ravel(), y.ravel(), np.zeros(9)])
    field = np.zeros_like(neutral)
    field[4, 2] = 10.0
    faces = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [3, 4, 7], [3, 7, 6], [4, 5, 8], [4, 8, 7]])
    text = viewer.page_html(neutral, field, faces, title="<b>plane</b>")
    assert "&lt;b&gt;plane&lt;/b&gt;" in text and '"texture": null' in text


@pytest.mark.parametrize("kwargs, message", [
    (dict(field=np.zeros((4, 3))), "field"),
    (dict(uv=np.zeros((9, 2))), "uv and image"),
    (dict(magnitude=2.0), "magnitude"),
    (dict(max_magnitude=0.0), "max_magnitude"),
    (dict(faces=np.zeros((0, 3), dtype=int)), "faces"),
])
def test_bad_page_input_names_the_argument(kwargs, message):
    arguments = dict(neutral=np.random.default_rng(0).normal(size=(9, 3)), field=np.zeros((9, 3)),
                     faces=np.array([[0, 1, 2], [2, 3, 4]]))
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=message):
        viewer.page_html(**arguments)


def test_write_html_wants_an_html_file(tmp_path):
    with pytest.raises(ValueError, match="html"):
        viewer.write_html(tmp_path / "page.txt", np.zeros((3, 3)), np.zeros((3, 3)), [[0, 1, 2]])
