"""tpscore.batch: job discovery, manifests, the results table, and batches on a real
dask.distributed LocalCluster (two worker processes) with scans from make_scans.py."""
from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

import tpscore
from tpscore import batch
from tpscore.face import io
from tpscore.batch import AdaptJob, Job, Progress, TransferJob
from tpscore.batch.work import WorkSettings, read_record

# a small grid keeps each transfer well under a second; the pipeline is the default one
GRID = (64, 64)


# --------------------------------------------------------------------------- without scans

def _fake_layout(root: Path, subjects, codes) -> Path:
    """Discovery reads names only: empty files stand in for scans."""
    for s in subjects:
        folder = root / f"bs{s:03d}"
        folder.mkdir(parents=True)
        for code in codes:
            (folder / f"bs{s:03d}_{code}.bnt").touch()
    return root


def test_transfer_jobs_choose_pairs_and_codes(tmp_path):
    root = _fake_layout(tmp_path, range(4), ["N_N_0", "LFAU_12_0", "UFAU_1_0", "LFAU_9_0", "E_SADNESS_0", "YR_R90_0",
                                             "CAU_A22A25_0", "UFAU_43_0", "O_GLASSES_0"])
    jobs = batch.transfer_jobs(root, pairs="next-1")
    # every AU, combination and emotion code maps to its request; poses and occlusions are no expression
    assert {j.action_units for j in jobs} == {"12", "1", "9", "sadness", "22+25", "43"}
    pairs = {(j.name[:5], j.name.split("__")[1]) for j in jobs}
    assert pairs == {("bs000", "bs001"), ("bs001", "bs002"), ("bs002", "bs003"), ("bs003", "bs000")}
    job = next(j for j in jobs if j.name == "bs003_LFAU_12_0__bs000")
    assert job.source_neutral.endswith("bs003/bs003_N_N_0.bnt") and job.target.endswith("bs000/bs000_N_N_0.bnt")
    assert job.truth.endswith("bs000/bs000_LFAU_12_0.bnt")

    every = batch.transfer_jobs(root, action_units=["AU12"], sources=[1], targets=[0, 1, 3], pairs="all")
    assert [j.name for j in every] == ["bs001_LFAU_12_0__bs000", "bs001_LFAU_12_0__bs003"]
    two = batch.transfer_jobs(root, action_units=["12"], sources=[2], pairs="next-2")
    assert [j.name.split("__")[1] for j in two] == ["bs003", "bs000"]  # wraps around


def test_transfer_jobs_refuse_bad_selections(tmp_path):
    root = _fake_layout(tmp_path, range(2), ["N_N_0", "LFAU_12_0"])
    with pytest.raises(ValueError, match="unknown action unit"):
        batch.transfer_jobs(root, action_units=["99"])
    with pytest.raises(ValueError, match="action_units: no source scan .* 'sadness'"):
        batch.transfer_jobs(root, action_units=["sadness"])
    with pytest.raises(ValueError, match=r"sources: subject\(s\) \[7\]"):
        batch.transfer_jobs(root, sources=[7])
    with pytest.raises(ValueError, match="pairs must be"):
        batch.transfer_jobs(root, pairs="next-0")
    with pytest.raises(ValueError, match="folder not found"):
        batch.transfer_jobs(tmp_path / "missing")
    with pytest.raises(ValueError, match="no bsNNN"):
        batch.transfer_jobs(root / "bs000")


def test_manifest_rows_become_jobs(tmp_path):
    (tmp_path / "m.csv").write_text(
        "kind,name,source_neutral,source_expressive,target,au,magnitude,method,options,scan,template,template_landmarks\n"
        "transfer,,a/n.bnt,a/e.bnt,b/n.bnt,12,0.5,published,,,,\n"
        "# a comment row\n"
        "transfer,mine,a/n.bnt,a/e.bnt,b/n.bnt,1+4,,,mirror_average=false; motion.rest_weight=0.5,,,\n"
        "\n"
        "adapt,,,,,,,,levels=3,s/x.bnt,t.obj,t.lm3\n")
    jobs = batch.read_manifest(tmp_path / "m.csv")
    assert [type(j) for j in jobs] == [TransferJob, TransferJob, AdaptJob]
    assert jobs[0].name == "e__n_m0.5" and jobs[0].options.method == "published" and jobs[0].magnitude == 0.5
    assert jobs[0].source_neutral == str(tmp_path / "a" / "n.bnt")  # relative to the manifest
    assert jobs[1].options.mirror_average is False and jobs[1].options.motion.rest_weight == 0.5
    assert jobs[2].name == "x" and jobs[2].options == (("levels", 3),)
    assert jobs[1].spec_hash != TransferJob("mine", *(jobs[1].source_neutral, jobs[1].source_expressive,
                                                      jobs[1].target), "1+4").spec_hash


@pytest.mark.parametrize("row, message", [
    ("transfer,,a.bnt,b.bnt,c.bnt,,", "line 2: a transfer row needs au"),
    ("transfer,x,a.bnt,b.bnt,c.bnt,12,motion.nope=1", "line 2: options: .*nope"),
    ("transfer,x,a.bnt,b.bnt,c.bnt,12,flux=1", "line 2: options: 'flux' is not a TransferOptions field"),
    ("transfer,../x,a.bnt,b.bnt,c.bnt,12,", "line 2: name '../x' cannot name an output file"),
    ("transfer,x,a.bnt,b.bnt,c.bnt,12,\ntransfer,x,a.bnt,b.bnt,c.bnt,1,", "line 3: name 'x' is already"),
    ("fit,x,a.bnt,b.bnt,c.bnt,12,", "kind must be 'transfer' or 'adapt'"),
])
def test_manifest_errors_name_the_file_and_line(tmp_path, row, message):
    path = tmp_path / "jobs.csv"
    path.write_text("kind,name,source_neutral,source_expressive,target,au,options\n" + row + "\n")
    with pytest.raises(ValueError, match=message) as caught:
        batch.read_manifest(path)
    assert "jobs.csv" in str(caught.value)


def test_manifest_unknown_column_and_missing_file(tmp_path):
    (tmp_path / "m.csv").write_text("source,target\nx,y\n")
    with pytest.raises(ValueError, match="unknown column"):
        batch.read_manifest(tmp_path / "m.csv")
    with pytest.raises(ValueError, match="manifest not found"):
        batch.read_manifest(tmp_path / "none.csv")


def test_adapt_job_refuses_unknown_options(tmp_path):
    with pytest.raises(ValueError, match="'levls' not a field of tpscore.AdaptOptions"):
        AdaptJob("x", "s.bnt", "t.obj", "t.lm3", options={"levls": 3})


def test_a_job_with_a_missing_input_fails_with_its_file_named(tmp_path):
    job = TransferJob("j", tmp_path / "a.bnt", tmp_path / "b.bnt", tmp_path / "c.bnt", "12")
    record = batch.execute(job, WorkSettings(str(tmp_path)))
    assert record["status"] == "failed" and "a.bnt" in record["error"] and "not found" in record["error"]
    assert read_record(tmp_path, "j")["error"] == record["error"]
    assert not (tmp_path / "j.npz").exists()


def test_run_refuses_bad_arguments_before_starting_dask(tmp_path):
    job = TransferJob("j", "a.bnt", "b.bnt", "c.bnt", "12")
    with pytest.raises(ValueError, match="names must be unique"):
        batch.run([job, job], tmp_path)
    with pytest.raises(ValueError, match="workers must be a whole number"):
        batch.run([job], tmp_path, workers=0)
    with pytest.raises(ValueError, match="gt_faces: .*file not found"):
        batch.run([job], tmp_path, gt_faces=tmp_path / "none.npz")
    (tmp_path / "file").touch()
    with pytest.raises(ValueError, match="is a file, not a folder"):
        batch.run([job], tmp_path / "file")


@pytest.mark.parametrize("arguments, message", [
    ([], "give a folder DIR or --manifest CSV"),
    (["DIR", "--manifest", "m.csv"], "give a folder DIR or --manifest CSV"),
    (["DIR", "--kind", "adapt", "--template", "t.obj"], "--kind adapt takes --template and --template-landmarks together"),
    (["DIR", "--sources", "0-x"], "--sources must look like 0-9,12"),
    (["DIR", "--grid", "150"], "--grid must look like 150x150"),
])
def test_batch_command_errors_are_one_line(tmp_path, capsys, arguments, message):
    from tpscore.cli import main

    arguments = [str(tmp_path) if a == "DIR" else a for a in arguments]
    assert main(["batch", *arguments, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tpscore: error:") and message in err and err.count("\n") == 1


def test_results_table_round_trips(tmp_path):
    rows = [dict(name="a", kind="transfer", status="done", error="", seconds=0.1 + 0.2, residual_ratio=1 / 3,
                 stage_seconds={"model": 0.25}),
            dict(name="b", kind="transfer", status="failed", error="'x.bnt': truncated, badly", seconds=None)]
    paths = batch.write_table(rows, tmp_path / "results")
    back = batch.read_table(paths[0])
    assert [r["name"] for r in back] == ["a", "b"]
    assert float(back[0]["seconds"]) == 0.1 + 0.2 and float(back[0]["residual_ratio"]) == 1 / 3  # exact
    assert json.loads(back[0]["stage_seconds"]) == {"model": 0.25}
    assert back[1]["error"] == "'x.bnt': truncated, badly" and back[1]["seconds"] == ""
    if importlib.util.find_spec("pyarrow"):
        import pyarrow.parquet as pq
        assert pq.read_table(paths[1]).column("residual_ratio").to_pylist() == [1 / 3, None]
    assert not list(tmp_path.glob(".*.tmp"))


def test_progress_writes_log_lines_when_not_a_terminal():
    import io
    stream = io.StringIO()
    meter = Progress(3, stream=stream, every=0.0)
    for status in ("done", "failed", "done"):
        meter.update(status)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 3 and "\r" not in stream.getvalue()
    assert lines[-1].split("] ")[1].startswith("3/3 jobs, 1 failed")


# --------------------------------------------------------------------------- with scans and Dask

def _score_module(shared):
    spec = importlib.util.spec_from_file_location("score_transfer", shared / "tools" / "score_transfer.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def scans(shared, tmp_path_factory):
    """Three subjects, neutral and AU12, without colour images (fewer, faster jobs)."""
    root = tmp_path_factory.mktemp("bosphorus")
    subprocess.run([sys.executable, str(shared / "tools" / "make_scans.py"), str(root), "--subjects", "0", "1", "2",
                    "--expressions", "N_N_0", "LFAU_12_0", "--texture-scale", "0", "--spacing-mm", "1.5"],
                   check=True, stdout=subprocess.DEVNULL)
    return root


@pytest.fixture(scope="module")
def gt_faces(shared):
    return shared / "data" / "ict-facekit" / "face_model.npz"


@pytest.fixture(scope="module")
def client():
    distributed = pytest.importorskip("distributed")
    import dask

    # a task whose worker dies twice is given up (Dask's default waits for four deaths,
    # each a worker restart of seconds); one death is still survived
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                           dashboard_address=None)
    client = distributed.Client(cluster)
    yield client
    client.close()
    cluster.close()


def _serial(job, shared, gt_faces):
    """The same transfer and score in this process, without the engine."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        grids = [tpscore.load_scan(p, shape=job.grid) for p in (job.source_neutral, job.source_expressive, job.target)]
        result = tpscore.transfer(*grids, job.action_units, job.magnitude, options=job.options)
    stem = lambda p: os.path.splitext(p)[0]  # noqa: E731
    score = _score_module(shared).score(result.vertices, result.neutral, stem(job.target) + "_gt.npz",
                                        stem(job.truth) + "_gt.npz", np.load(gt_faces)["faces"], mask=result.mask)
    return result.to_npz_dict(), score


@pytest.fixture(scope="module")
def first_run(scans, client, gt_faces, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    jobs = batch.transfer_jobs(scans, pairs="next-1", grid=GRID)
    report = batch.run(jobs, out, client=client, gt_faces=gt_faces, progress=False)
    return jobs, out, report


def test_batch_equals_serial_transfers_bit_for_bit(first_run, shared, gt_faces):
    jobs, out, report = first_run
    assert report.counts() == {"done": 3, "failed": 0, "skipped": 0, "not run": 0}
    rows = {row["name"]: row for row in report.rows}
    for job in jobs:
        arrays, score = _serial(job, shared, gt_faces)
        with np.load(out / f"{job.name}.npz") as saved:
            for key, value in arrays.items():
                assert np.array_equal(saved[key], value, equal_nan=value.dtype.kind == "f"), (job.name, key)
        row = rows[job.name]
        # the batch's scorer against the reference scorer: the same numbers, not close ones
        assert row["score_source"] == "sidecar"
        assert (row["residual_ratio"], row["rms_mm"], row["leak_mm"], row["pred_missing"]) == (
            score["residual_ratio"], score["rms_mm"], score["leak_rms_mm"], score["n_pred_missing"])
        assert 0.0 < row["residual_ratio"] < 1.0  # a transfer, better than the neutral target
    table = batch.read_table(out / "results.csv")
    assert [r["name"] for r in table] == [j.name for j in jobs]
    assert all(float(r["residual_ratio"]) == rows[r["name"]]["residual_ratio"] for r in table)
    assert "12" in report.summary() and "done 3" in report.summary()


def test_rerun_skips_what_is_done_and_redoes_a_damaged_output(first_run, client, gt_faces):
    jobs, out, _ = first_run
    stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}
    again = batch.run(jobs, out, client=client, gt_faces=gt_faces, progress=False)
    assert again.counts()["skipped"] == 3 and again.counts()["done"] == 0
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")} == stamps
    assert [r["residual_ratio"] for r in again.rows] == [r["residual_ratio"] for r in first_run[2].rows]

    damaged = out / f"{jobs[1].name}.npz"
    data = damaged.read_bytes()
    damaged.write_bytes(data[: len(data) // 2])  # a cut-off file: what a crash mid-write would leave
    changed = TransferJob(**{**jobs[2].__dict__, "options": tpscore.TransferOptions(mirror_average=False)})
    third = batch.run([jobs[0], jobs[1], changed], out, client=client, gt_faces=gt_faces, progress=False)
    assert [r["status"] for r in third.rows] == ["skipped", "done", "done"]
    with np.load(damaged) as repaired:
        assert repaired["vertices"].shape == GRID + (3,)


@pytest.fixture()
def damaged_scans(scans, tmp_path):
    root = tmp_path / "scans"
    shutil.copytree(scans, root)
    bnt = root / "bs001" / "bs001_N_N_0.bnt"
    bnt.write_bytes(bnt.read_bytes()[:5000])
    (root / "bs002" / "bs002_LFAU_12_0.lm3").unlink()
    return root


def test_a_corrupted_scan_fails_only_its_jobs(damaged_scans, client, gt_faces, tmp_path):
    jobs = batch.transfer_jobs(damaged_scans, pairs="all", grid=GRID)
    report = batch.run(jobs, tmp_path / "out", client=client, gt_faces=gt_faces, progress=False)
    status = {row["name"]: row["status"] for row in report.rows}
    # bs001's neutral scan is cut off: every job that reads it fails; bs002's expressive
    # scan has no landmark file: its landmarks are detected, and its jobs run and say so
    assert status == {"bs000_LFAU_12_0__bs001": "failed", "bs000_LFAU_12_0__bs002": "done",
                      "bs001_LFAU_12_0__bs000": "failed", "bs001_LFAU_12_0__bs002": "failed",
                      "bs002_LFAU_12_0__bs000": "done", "bs002_LFAU_12_0__bs001": "failed"}
    table = {r["name"]: r for r in batch.read_table(tmp_path / "out" / "results.csv")}
    assert "bs001_N_N_0.bnt" in table["bs001_LFAU_12_0__bs000"]["error"]
    assert "truncated .bnt data" in table["bs001_LFAU_12_0__bs000"]["error"]
    detected = table["bs002_LFAU_12_0__bs000"]
    assert "bs002_LFAU_12_0.bnt" in detected["warnings"] and "landmarks detected" in detected["warnings"]
    assert "landmarks detected" not in table["bs000_LFAU_12_0__bs002"]["warnings"]
    assert all("\n" not in r["error"] for r in table.values())
    outputs = sorted(p.name for p in (tmp_path / "out").glob("*.npz"))
    assert outputs == ["bs000_LFAU_12_0__bs002.npz", "bs002_LFAU_12_0__bs000.npz"]


def test_a_scores_only_job_is_resumed_from_its_record(scans, tmp_path):
    job = batch.transfer_jobs(scans, pairs="next-1", grid=GRID)[0]
    job = TransferJob(**{**job.__dict__, "save": False})
    # no sidecar triangles: with truth, the job is scored against the target's own scan
    record = batch.execute(job, WorkSettings(str(tmp_path), truth=True))
    assert record["status"] == "done" and record["output"] == "" and not list(tmp_path.glob("*.npz"))
    assert record["score_source"] == "scan" and 0.0 < record["residual_ratio"] < 1.0
    skipped, to_run = batch.plan([job], tmp_path)
    assert [r["name"] for r in skipped] == [job.name] and to_run == []
    kept = TransferJob(**{**job.__dict__, "save": True})  # now asked for its output: run again
    assert batch.plan([kept], tmp_path)[1] == [kept]


class _KillAWorkerMidJob(Progress):
    """At the first finished job, kills a worker process that is running another one."""

    def __init__(self, total, client):
        super().__init__(total, enabled=False)
        self.client = client
        self.killed = None

    def update(self, status):
        super().update(status)
        if self.killed is not None:
            return
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            running = self.client.run(lambda dask_worker: sorted(ts.key for ts in dask_worker.state.executing))
            busy = [(address, keys) for address, keys in running.items() if keys]
            if busy:
                address, keys = busy[0]
                time.sleep(0.3)  # well inside a job of about a second
                pid = self.client.run(os.getpid, workers=[address])[address]
                os.kill(pid, signal.SIGKILL)
                self.killed = (pid, keys[0])
                return
            time.sleep(0.05)


def test_a_worker_killed_mid_job_loses_nothing(scans, client, gt_faces, shared, tmp_path):
    jobs = batch.transfer_jobs(scans, pairs="next-1", grid=GRID)
    meter = _KillAWorkerMidJob(len(jobs), client)
    report = batch.run(jobs, tmp_path, client=client, gt_faces=gt_faces, progress=meter)
    assert meter.killed is not None, "no worker was running a job to kill"
    pid, key = meter.killed
    assert report.counts()["done"] == len(jobs) == 3
    assert sorted(r["name"] for r in report.rows) == sorted(j.name for j in jobs)  # each once
    assert sorted(p.stem for p in tmp_path.glob("*.npz")) == sorted(j.name for j in jobs)
    assert not list(tmp_path.rglob("*.tmp"))
    # the job the dead worker was running was done again elsewhere, and is right
    victim = next(j for j in jobs if key == f"tpscore-batch-{j.name}-{j.spec_hash}")
    row = next(r for r in report.rows if r["name"] == victim.name)
    assert row["worker"] is not None
    arrays, score = _serial(victim, shared, gt_faces)
    with np.load(tmp_path / f"{victim.name}.npz") as saved:
        assert np.array_equal(saved["vertices"], arrays["vertices"], equal_nan=True)
    assert row["residual_ratio"] == score["residual_ratio"]
    # the nanny replaced the dead process
    deadline = time.monotonic() + 30
    while len(client.nthreads()) < 2 and time.monotonic() < deadline:
        time.sleep(0.2)
    assert len(client.nthreads()) == 2 and pid not in client.run(os.getpid).values()


@dataclass(frozen=True)
class _QuickJob(Job):
    """Computes nothing; its record is its result."""

    name: str
    kind: ClassVar[str] = "quick"
    save: ClassVar[bool] = False

    def columns(self):
        return {}

    def run(self, context):
        return {}


@dataclass(frozen=True)
class _CrashJob(_QuickJob):
    """Takes down the worker process that runs it, as a segfault or the kernel's
    out-of-memory killer would."""

    def run(self, context):
        os._exit(3)


def test_a_job_that_kills_every_worker_it_runs_on_fails_alone(client, tmp_path):
    jobs = [_QuickJob("before"), _CrashJob("crash"), _QuickJob("after")]
    # one job in flight at a time: no innocent job is queued on a worker as it dies
    report = batch.run(jobs, tmp_path, client=client, max_in_flight=1, progress=False)
    status = {row["name"]: row for row in report.rows}
    assert status["before"]["status"] == status["after"]["status"] == "done"
    assert status["crash"]["status"] == "failed" and "KilledWorker" in status["crash"]["error"]
    assert read_record(tmp_path, "crash") is None  # it never finished: a rerun tries it again
    deadline = time.monotonic() + 60
    while len(client.nthreads()) < 2 and time.monotonic() < deadline:
        time.sleep(0.2)  # leave the cluster whole for the tests after this one


def test_ctrl_c_leaves_complete_outputs_and_the_rerun_resumes(scans, client, gt_faces, tmp_path):
    out = tmp_path / "out"
    command = [sys.executable, "-m", "tpscore.cli", "batch", str(scans), "--out", str(out), "--pairs", "all",
               "--grid", f"{GRID[0]}x{GRID[1]}", "--workers", "2", "--gt-faces", str(gt_faces)]
    # a session of its own: Ctrl-C at a terminal signals the whole foreground group,
    # the workers included, and so does killpg here
    # the interpreter's own environment: the installed tpscore (or the caller's PYTHONPATH)
    # and SIGINT at its default: a test run started in the background of a
    # non-interactive shell ignores SIGINT, its children inherit that, and Python
    # installs no KeyboardInterrupt handler when it starts with SIGINT ignored
    process = subprocess.Popen(command, start_new_session=True, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while not list((out / "records").glob("*.json")) and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.1)
    if process.poll() is not None:
        _, stderr = process.communicate()
        pytest.fail(f"the batch ended before it could be interrupted (exit {process.returncode}): {stderr}")
    os.killpg(process.pid, signal.SIGINT)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, stderr
    assert "interrupted" in stdout
    table = batch.read_table(out / "results.csv")
    assert len(table) == 6
    done = {r["name"] for r in table if r["status"] == "done"}
    assert 1 <= len(done) < 6 and {r["status"] for r in table} <= {"done", "not run"}
    # only complete outputs: each with its record, each readable
    assert sorted(p.stem for p in out.glob("*.npz")) == sorted(p.stem for p in (out / "records").glob("*.json"))
    for path in out.glob("*.npz"):
        with np.load(path) as data:
            assert data["vertices"].shape == GRID + (3,)
    assert not list(out.rglob("*.tmp"))
    finished = {p.stem for p in out.glob("*.npz")}
    assert done == finished  # jobs finished while the interrupt was handled are in the table too

    # the rerun (on the tests' cluster, to save starting another) skips exactly those
    again = batch.run(batch.transfer_jobs(scans, pairs="all", grid=GRID), out, client=client, gt_faces=gt_faces,
                      progress=False)
    assert {r["name"] for r in again.rows if r["status"] == "skipped"} == finished
    assert again.counts()["done"] == 6 - len(finished)
    assert len(list((out / "records").glob("*.json"))) == 6


def test_adaptation_jobs_fit_the_template_to_each_scan(scans, shared, tmp_path):
    model = np.load(shared / "data" / "ict-facekit" / "face_model.npz")
    vertices, faces = model["neutral"].astype(np.float64), model["faces"].astype(np.int64)
    tpscore.write_mesh(tmp_path / "template.obj", vertices, faces)
    tpscore.write_lm3(tmp_path / "template.lm3", vertices[model["bosphorus_index"]])
    jobs = batch.adapt_jobs(scans, tmp_path / "template.obj", tmp_path / "template.lm3", subjects=[0],
                            codes=["N_N_0"], options={"levels": 2})
    assert [j.name for j in jobs] == ["bs000_N_N_0"]
    record = batch.execute(jobs[0], WorkSettings(str(tmp_path)))
    assert record["status"] == "done", record["error"]
    fitted, fitted_faces = tpscore.read_mesh(tmp_path / "bs000_N_N_0.obj")
    assert np.array_equal(fitted_faces, faces) and fitted.shape == vertices.shape
    # the fit follows the scan: within a few millimetres of the mesh it was made from
    # (the adaptation benchmark's defaults reach about 1.3 mm on these scans)
    assert record["score_source"] == "sidecar" and record["rms_mm"] < 3.0


def test_adapt_jobs_default_to_the_shipped_template_head(tmp_path):
    from tpscore import physics
    from tpscore.cli.batch import _jobs
    from tpscore.cli.main import build_parser

    root = _fake_layout(tmp_path / "scans", range(2), ["N_N_0"])
    out = tmp_path / "out"
    args = build_parser().parse_args(["batch", str(root), "--out", str(out), "--kind", "adapt"])
    jobs = _jobs(args)
    assert [j.name for j in jobs] == ["bs000_N_N_0", "bs001_N_N_0"]
    # the head is written where every worker sharing OUT reads it, with its landmarks
    head = physics.load_template()
    vertices, faces = io.read_mesh(jobs[0].template)
    assert np.array_equal(vertices, head.vertices) and np.array_equal(faces, head.faces)
    np.testing.assert_array_equal(io.read_landmarks(jobs[0].template_landmarks), head.landmarks)
    half = build_parser().parse_args(["batch", str(root), "--out", str(out), "--kind", "adapt", "--template", "t.obj"])
    with pytest.raises(ValueError, match="together"):
        _jobs(half)
