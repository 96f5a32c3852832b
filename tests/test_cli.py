import subprocess
import sys

import numpy as np
import pytest

from tpscore import datasets
from tpscore.face import io
from tpscore.cli import main


@pytest.fixture(scope="module")
def scan_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scans")
    paths = []
    truth = datasets.make_face(datasets.random_identity(datasets.DEMO_TARGET_SEED), {"12": 1.0})
    scans = list(datasets.demo_triplet("12", holes=1, noise_mm=0.1, seed=3)) + [truth]
    for name, scan in zip(("a", "b", "c", "d"), scans):
        io.write_bnt(folder / f"{name}.bnt", io.BntScan.from_points(scan.points, image_name=f"{name}.png"))
        io.write_lm3(folder / f"{name}.lm3", scan.landmarks)
        paths.append(folder / f"{name}.bnt")
    return paths


def test_transfer_writes_every_output(scan_files, tmp_path, capsys):
    a, b, c, d = scan_files
    out = tmp_path / "result.npz"
    code = main(["transfer", "--source-neutral", str(a), "--source-expr", str(b), "--target", str(c),
                 "--au", "12", "--magnitude", "0.8", "--out", str(out), "--mesh", str(tmp_path / "r.obj"),
                 "--png", str(tmp_path / "r.png"), "--gif", str(tmp_path / "r.gif"), "--truth", str(d)])
    assert code == 0
    printed = capsys.readouterr().out
    assert "transferred AU12" in printed
    # where the neutral target is off the true expressive surface, the result is closer
    # to it (measured with the default pipeline: 0.6 of the neutral's distance)
    line = printed.split("distance to the true expressive scan")[1].split("\n")[0]
    result_rms = float(line.split("rms ")[1].split()[0])
    neutral_rms = float(line.split("the neutral target: ")[1].split()[0])
    assert result_rms < 0.8 * neutral_rms
    with np.load(out) as data:
        vertices, neutral, mask = data["vertices"], data["neutral"], data["mask"]
    assert vertices.shape == neutral.shape == mask.shape + (3,)
    moved = np.linalg.norm(vertices - neutral, axis=2)[mask]
    assert 0.5 < moved.max() < 20.0
    vertices_obj, faces_obj = io.read_mesh(tmp_path / "r.obj")
    assert len(vertices_obj) == mask.sum() and len(faces_obj) > 0
    for picture in ("r.png", "r.gif"):
        assert (tmp_path / picture).stat().st_size > 1000


def test_errors_are_one_line_not_a_traceback(scan_files, tmp_path, capsys):
    a, b, c, _ = scan_files
    code = main(["transfer", "--source-neutral", str(a), "--source-expr", str(b),
                 "--target", str(tmp_path / "missing.bnt"), "--au", "12"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("tpscore: error:") and "missing.bnt" in err and "Traceback" not in err
    assert main(["transfer", "--source-neutral", str(a), "--source-expr", str(b),
                 "--target", str(c), "--au", "99"]) == 2
    assert "unknown action unit" in capsys.readouterr().err


def test_demo_writes_meshes_and_pictures(tmp_path):
    out = tmp_path / "demo"
    # the installed console script, as a user runs it
    run = subprocess.run([sys.executable, "-m", "tpscore.cli", "demo", "--out", str(out), "--quiet"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    for stem in ("au12", "au4", "sadness"):
        for suffix in ("npz", "obj", "ply"):
            assert (out / f"target_{stem}.{suffix}").stat().st_size > 1000
        assert (out / f"transfer_{stem}.png").stat().st_size > 1000
        assert (out / f"sweep_{stem}.gif").stat().st_size > 1000
    assert (out / "scans" / "target_neutral.bnt").is_file()
    # the physical skin: a fitted scan smiles, frowns and opens its jaw
    for stem in ("smile", "frown", "jaw"):
        assert (out / f"skin_{stem}.png").stat().st_size > 1000
    assert (out / "skin_expressions.gif").stat().st_size > 1000
