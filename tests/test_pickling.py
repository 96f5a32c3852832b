"""Fitted kernels and transfer results pickle and copy: a warp can be shipped to a
Dask worker, a process pool or joblib, and comes back giving the same results."""
import copy
import pickle

import numpy as np
import pytest
import scipy.sparse as sp

import tpscore
from tpscore.showcase import datasets


@pytest.fixture(scope="module")
def points():
    rng = np.random.default_rng(4)
    return rng.normal(size=(60, 3)) * 30, rng.normal(size=(500, 3)) * 30


def _fitted(points):
    centres, queries = points
    yield "TPS", tpscore.TPS(centres, centres + 1.5 * np.sin(centres / 20)), lambda f: f(queries)
    yield "RBF", tpscore.RBF(centres, np.cos(centres[:, :2] / 15), kernel="gaussian", epsilon=0.05,
                             smoothing=0.1), lambda f: f(queries)
    yield "CSRBF", tpscore.CSRBF(centres, np.sin(centres[:, 0] / 10), support=40.0), lambda f: f(queries)
    yield "KDTree", tpscore.KDTree(centres), lambda f: np.concatenate(f.query(queries, k=3), axis=1)
    scan = datasets.make_face(spacing_mm=3.0)
    mesh = tpscore.resample_scan(scan.points, scan.landmarks, (40, 40)).mesh()
    yield "MeshSurface", tpscore.MeshSurface(mesh.vertices, mesh.faces), lambda f: f.closest_point(queries).points
    laplacian = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(50, 50), format="csr")
    yield "SparseCholesky", tpscore.SparseCholesky(laplacian), lambda f: f.solve(np.arange(50.0))


@pytest.mark.parametrize("index", range(6))
def test_fitted_kernels_pickle_and_copy_to_the_same_results(points, index):
    name, fitted, use = list(_fitted(points))[index]
    expected = use(fitted)
    back = pickle.loads(pickle.dumps(fitted))
    assert type(back) is type(fitted)
    # the same build refits the same inputs to the bit
    assert np.array_equal(use(back), expected), name
    for copied in (copy.copy(fitted), copy.deepcopy(fitted)):
        assert np.array_equal(use(copied), expected), name


def test_a_transfer_result_pickles_with_its_animation(tmp_path):
    grids = [tpscore.resample_scan(scan.points, scan.landmarks) for scan in datasets.demo_triplet("12")]
    result = tpscore.transfer(*grids, "12", 0.7)
    back = pickle.loads(pickle.dumps(result))
    assert np.array_equal(back.vertices, result.vertices, equal_nan=True)
    assert np.array_equal(back.animation.frame(0.3), result.animation.frame(0.3), equal_nan=True)
    assert np.array_equal(back.measured_motion(), result.measured_motion(), equal_nan=True)
    assert back.animation.labels == result.animation.labels


def test_a_fitted_warp_ships_to_dask_workers(points):
    distributed = pytest.importorskip("distributed")
    centres, queries = points
    warp = tpscore.TPS(centres, centres * 1.01 + 0.5)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        remote = client.submit(lambda w, q: w(q), warp, queries).result(timeout=120)
    assert np.array_equal(remote, warp(queries))
