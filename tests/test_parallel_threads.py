"""Several devices in one process (issue 25 item 4: `parallel: {engine: threads}`, adseismic.solve.devices) and
`adseismic forward` on workers (item 2): two CPU device threads give the gradient of one process bit for bit, the same
FWI iterates, a forward bitwise equal to the one-process forward (either engine), per-device kept CUDA graphs, one
progress line per evaluation, one upload of each batch's data per band, and a failing device dropped with its batches
re-run on the others (the fault-free gradient). CI has no GPU: `devices: [cpu, cpu]` is what runs here."""

import threading
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import warp as wp
import yaml

from adseismic.accel import graphs
from adseismic.cli import main
from adseismic.config import load_fwi_config
from adseismic.config.parallel import ParallelConfig
from adseismic.inversion.fwi import _observed, band_filter, data_weights, prepare_fwi
from adseismic.solve import devices, distributed, pools, residency
from adseismic.solve.acoustic import gradient
from adseismic.solve.batch import shot_slices
from adseismic.solve.devices import DevicePool
from adseismic.solve.misfits import misfit as named_misfit

from .test_fwi import TINY

THREADS = {"engine": "threads", "devices": ["cpu", "cpu"]}


def write(tmp_path, cfg, name="fwi.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(cfg))
    return path


class Problem:
    """TINY's gradient problem (with n_shots shots) as inversion.fwi builds it: the band-passed wavelet and observed
    data, the weights, the gradient keywords; `one_process` is fwi's single-process loop over shot batches (resident:
    the observed data and weights as device arrays with the "l2" misfit formed there, as fwi runs it; else the misfit
    on the host, as for the other misfits)."""

    def __init__(self, tmp_path, n_shots=3):
        raw = dict(TINY, geometry=dict(TINY["geometry"], sources={"line": dict(TINY["geometry"]["sources"]["line"], count=n_shots)}))
        self.cfg = load_fwi_config(write(tmp_path, raw, "problem.yaml"))
        prep = prepare_fwi(self.cfg)
        self.scene, p = prep.scene, prep.plan
        band = self.cfg.inversion.bands[0]
        self.obs = band_filter(_observed(self.cfg, prep, tmp_path, False), p.dt, band)
        wavelet = band_filter(self.scene.wavelet, p.dt, band)
        self.amp = np.broadcast_to(wavelet, self.scene.source_amplitudes.shape).copy()
        self.weights = data_weights(self.scene, self.cfg.inversion, self.cfg.forward.geometry)
        self.kw = dict(order=p.order, pml_width=p.pml_width, pml_reflection=p.pml_reflection, pml_velocity=prep.bounds[1],
                       free_surface=p.free_surface, device=p.device, precision=p.precision, memory_budget=None, pml_frequency=band[1] / 2)  # fmt: skip
        self.p, self.n_shots = p, n_shots
        self.model = self.scene.model.values * 1.02  # away from the start model: every term of the gradient non-zero

    def batches(self, per_batch=1):
        s = self.scene
        return [{"amplitudes": self.amp[sl], "sources": s.source_locations[sl], "receivers": s.receiver_locations[sl],
                 "weights": self.weights[sl], "observed": self.obs[sl], "first": sl.start}
                for sl in shot_slices(self.n_shots, per_batch)]  # fmt: skip

    def params(self):
        return {"dx": self.p.dx, "dt": self.p.dt, "misfit": "l2", "illumination": False, "kw": self.kw}

    def one_process(self, per_batch=None, resident=False):
        s, p = self.scene, self.p
        loss, grad = 0.0, np.zeros(self.model.shape)
        for sl in shot_slices(self.n_shots, per_batch):
            w_sl, o_sl = self.weights[sl], self.obs[sl]
            if resident:
                dev = self.kw["device"]
                misfit = {"observed": wp.array(o_sl, dtype=wp.float64, device=dev), "misfit": "l2",
                          "weights": wp.array(w_sl, dtype=wp.float64, device=dev)}
            else:
                def weighted(syn, w_sl=w_sl, o_sl=o_sl):
                    j, adj = named_misfit("l2", w_sl * syn, w_sl * o_sl, p.dt)
                    return j, w_sl * adj

                misfit = {"misfit": weighted}
            r = gradient(self.model, p.dx, p.dt, self.amp[sl], s.source_locations[sl], s.receiver_locations[sl], **misfit, **self.kw)
            loss += r.loss
            grad += r.velocity
        return loss, grad


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    return Problem(tmp_path_factory.mktemp("problem"))


def where(model, data, params):
    """A task that reports where it ran: (thread name without its executor suffix, device)."""
    return threading.current_thread().name.split("_")[0], params["device"]


def uploads(token):
    """{(batch key, device): uploads} of the pool `token` in this process (solve.residency.resident's count)."""
    return {at: n for at, n in residency.UPLOADS.items() if at[0].startswith(f"{token}-")}


def test_two_cpu_device_threads_give_the_gradient_of_one_process(problem):
    default = wp.get_device()
    with DevicePool(ParallelConfig(**THREADS), "cpu", problem.n_shots) as pool:
        assert pool.workers() == ["0: cpu", "1: cpu"]
        pool.keep(problem.batches())
        rs = pool.evaluate(problem.model, problem.params())
        again = distributed.reduce_in_order(pool.evaluate(problem.model, problem.params()), problem.model.shape)
        probe = pool.evaluate(problem.model, problem.params(), fn=where)
        # resident data: each batch's observed data and weights went to its device once, in the first evaluation
        first = {(f"{pool.token}-1-{k}", "cpu"): 1 for k in range(3)}
        assert uploads(pool.token) == first and {at for at in residency.RESIDENT if at[0].startswith(pool.token)} == set(first)
        pool.keep(problem.batches(per_batch=3))  # a new band: the previous band's device arrays are freed
        assert not [at for at in residency.RESIDENT if at[0].startswith(pool.token)] and not uploads(pool.token)
        pool.evaluate(problem.model, problem.params())
        assert [at for at in residency.RESIDENT if at[0].startswith(pool.token)] == [(f"{pool.token}-2-0", "cpu")]
    assert not [at for at in residency.RESIDENT if at[0].startswith(pool.token)] and not uploads(pool.token)  # and at close
    assert wp.get_device() == default  # the caller's default device, whatever the threads' scopes did to it
    assert [r["first"] for r in rs] == [0, 1, 2]  # batch order
    assert probe == [("adseismic-0-cpu", "cpu"), ("adseismic-1-cpu", "cpu"), ("adseismic-0-cpu", "cpu")]  # round-robin
    loss, grad, _ = distributed.reduce_in_order(rs, problem.model.shape)
    # the same batches in one process as fwi runs them (resident data, l2 on the device): bit for bit
    one_loss, one_grad = problem.one_process(per_batch=1, resident=True)
    assert loss == one_loss
    np.testing.assert_array_equal(grad, one_grad)
    # one batch of all shots, misfit on the host: the 1e-12 (float64 round-off of sums in another order)
    all_loss, all_grad = problem.one_process()
    assert abs(loss - all_loss) <= 1e-12 * abs(all_loss)
    assert np.linalg.norm(grad - all_grad) <= 1e-12 * np.linalg.norm(all_grad)
    assert again[0] == loss and np.array_equal(again[1], grad)  # the data stayed on the devices: only the model went in


def test_a_failing_device_is_dropped_and_its_batches_rerun_on_the_others(problem, monkeypatch, caplog):
    # an injected CUDA-like error in every batch of device 1 (thread adseismic-1-*), in the first evaluation (whose
    # first batches run one device after the other) and before any of its data reached the device
    def failing_on_device_1(data, device, misfit, resident=residency.resident):
        if threading.current_thread().name.startswith("adseismic-1-"):
            raise RuntimeError("CUDA error 700: an illegal memory access was encountered (injected)")
        return resident(data, device, misfit)

    monkeypatch.setattr(residency, "resident", failing_on_device_1)
    with DevicePool(ParallelConfig(**THREADS), "cpu", problem.n_shots) as pool:
        pool.keep(problem.batches())
        with caplog.at_level("WARNING", logger="adseismic.solve.devices"):
            rs = pool.evaluate(problem.model, problem.params())
        assert pool.workers() == ["0: cpu"]
        probe = pool.evaluate(problem.model, problem.params(), fn=where)
    assert [r["first"] for r in rs] == [0, 1, 2]
    loss, grad, _ = distributed.reduce_in_order(rs, problem.model.shape)
    one_loss, one_grad = problem.one_process(per_batch=1, resident=True)  # the fault-free result, bit for bit
    assert loss == one_loss
    np.testing.assert_array_equal(grad, one_grad)
    [warning] = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "device 1: cpu (RuntimeError: CUDA error 700" in warning and "dropped for the rest of the run" in warning
    assert probe == [("adseismic-0-cpu", "cpu")] * 3  # later evaluations on the remaining device only


def test_device_faults_move_queued_batches_other_errors_are_raised_as_they_are(caplog):
    # no simulation: tasks that report where they ran; device 1 fails on its first batch while its other batches
    # wait in its queue: they move to device 0 (cancelled there, or failing there if already started), and the
    # results stay in batch order
    def task(model, data, params):
        if threading.current_thread().name.startswith("adseismic-1-"):
            raise MemoryError("out of memory on device (injected)")
        return data["first"], where(model, data, params)[0]

    with DevicePool(ParallelConfig(**THREADS), "cpu", 6) as pool, caplog.at_level("WARNING", logger="adseismic.solve.devices"):
        pool.keep([{"first": k} for k in range(6)])
        assert pool.evaluate(None, {}, fn=task) == [(k, "adseismic-0-cpu") for k in range(6)]
        assert "its 3 shot batch(es) re-run on cpu" in caplog.text
        pool.keep([{"first": k} for k in range(2)])  # the next band: every batch on device 0

        def bad_input(model, data, params):
            raise ValueError("receiver_locations[0, 3] lies outside the grid")

        with pytest.raises(ValueError, match="outside the grid"):  # bad input is no device's fault: raised as it is
            pool.evaluate(None, {}, fn=bad_input)
        assert pool.workers() == ["0: cpu"]

        def broken(model, data, params):
            raise RuntimeError("CUDA error 999: unknown error (injected)")

        with pytest.raises(RuntimeError, match=r"every device failed; the last, 0: cpu \(RuntimeError: CUDA error 999.*parallel.devices"):
            pool.evaluate(None, {}, fn=broken)


def test_kept_graph_loops_are_per_device():
    graphs.release()
    keys = [("gradient", "k", (31, 41), "cuda:0", 100), ("gradient", "k", (31, 41), "cuda:1", 100)]
    loops = [graphs.keep(SimpleNamespace(key=k)) for k in keys]
    try:
        assert [graphs.kept(k) for k in keys] == loops  # two devices: neither evicts the other
        assert graphs.kept(("gradient", "k", (31, 41), "cuda:0", 200)) is None  # a miss frees its device's loop only
        assert graphs.kept(keys[0]) is None and graphs.kept(keys[1]) is loops[1]
    finally:
        graphs.release()


def assert_fwi_iterates_do_not_depend_on(parallel: dict, tmp_path, rtol: float, per_batch: int | None = 1) -> str:
    """A tiny FWI (3 shots) in one process and with the `parallel` section (2 workers), shots_per_batch = per_batch (None:
    unset): the same iterates, misfits and final model (to rtol; 0 asks for bitwise); returns the parallel run's fwi.log."""
    inversion = dict(TINY["inversion"], iterations=2, bands=[4.0], **({} if per_batch is None else {"shots_per_batch": per_batch}))
    cfg = dict(TINY, inversion=inversion)
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(["fwi", str(write(tmp_path, cfg, "one.yaml")), "-o", str(one), "-q"]) == 0
    assert main(["fwi", str(write(tmp_path, dict(cfg, parallel=parallel), "two.yaml")), "-o", str(two), "-q"]) == 0
    log = (two / "fwi.log").read_text()
    batches = 3 if per_batch == 1 else 2  # unset: one batch per worker, 2 + 1 shots
    assert f"evaluation 1: {batches} shot batch(es) on 2 worker(s) in" in log  # progress over the workers, in fwi.log
    with h5py.File(one / "history.h5") as a, h5py.File(two / "history.h5") as b:
        assert sorted(a["band0"]) == sorted(b["band0"]) == ["iter0001", "iter0002"]
        for it in a["band0"]:
            np.testing.assert_allclose(b[f"band0/{it}/model"][...], a[f"band0/{it}/model"][...], rtol=rtol, atol=0)
            assert b[f"band0/{it}"].attrs["misfit"] == pytest.approx(a[f"band0/{it}"].attrs["misfit"], rel=rtol, abs=0)
    with h5py.File(one / "model.h5") as a, h5py.File(two / "model.h5") as b:
        np.testing.assert_allclose(b["model"][...], a["model"][...], rtol=rtol, atol=0)
    return log


def test_fwi_iterates_do_not_depend_on_the_device_threads(tmp_path):
    """The same batches and sums in the same order: the same iterates, bit for bit."""
    log = assert_fwi_iterates_do_not_depend_on(THREADS, tmp_path, rtol=0.0)
    assert "parallel: 2 thread(s) in this process on cpu, cpu" in log


def test_a_pool_runs_one_batch_per_worker_unless_shots_per_batch_is_set(tmp_path):
    """Without inversion.shots_per_batch a pool runs one batch per worker (solve.pools.pool_shots_per_batch), as one
    process runs all shots at once: the one-process iterates to float64 round-off (the shots' gradients summed in
    other groups: the iterates of float64 runs differ by ~1e-16 relative, far below 1e-12)."""
    log = assert_fwi_iterates_do_not_depend_on(THREADS, tmp_path, rtol=1e-12, per_batch=None)
    assert "inversion.shots_per_batch: 2 (one batch per worker of the pool" in log


FORWARD = {
    "model": {"kind": "gaussian_anomaly", "shape": [31, 41], "spacing": 20.0, "background": 2000.0, "perturbation": 200.0,
              "center": [300.0, 400.0], "radius": 80.0},
    "geometry": {"sources": {"line": {"start": {"x": 100, "z": 20}, "end": {"x": 700, "z": 20}, "count": 5}},
                 "receivers": {"line": {"start": {"x": 0, "z": 10}, "end": {"x": 800, "z": 10}, "count": 21}}},
    "wavelet": {"kind": "ricker", "peak_frequency": 6.0},
    "simulation": {"order": 4, "pml_width": 8},
    "output": {"snapshot_interval": 0.1},
}  # fmt: skip


def _engines():
    dask = pytest.param({"engine": "dask", "devices": ["cpu", "cpu"]}, id="dask",
                        marks=pytest.mark.skipif(not _has_dask(), reason="dask not installed"))
    return [pytest.param(THREADS, id="threads"), dask]


def _has_dask():
    try:
        import distributed  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.mark.parametrize("parallel", _engines())
def test_forward_on_workers_equals_the_one_process_forward_bit_for_bit(tmp_path, parallel):
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(["forward", str(write(tmp_path, FORWARD, "one.yaml")), "-o", str(one), "-q"]) == 0
    assert main(["forward", str(write(tmp_path, dict(FORWARD, parallel=parallel), "two.yaml")), "-o", str(two), "-q"]) == 0
    assert "forward: 4 shot batch(es) on 2 worker(s) in" in (two / "forward.log").read_text()  # 1 + 1 shots, then 2 + 1
    with h5py.File(one / "data.h5") as a, h5py.File(two / "data.h5") as b:
        assert a["receiver_data"].shape == (5, 21, a["receiver_data"].shape[2])
        np.testing.assert_array_equal(b["receiver_data"][...], a["receiver_data"][...])  # gathered in shot order
        np.testing.assert_array_equal(b["snapshots"][...], a["snapshots"][...])


def test_elastic_forward_on_device_threads_equals_one_process(tmp_path):
    from adseismic.config.forward import load_config
    from adseismic.scene import build_scene, plan_scene, run_forward

    raw = dict(FORWARD, physics="elastic", output={"snapshot_interval": 0.0},
               model={"vp": FORWARD["model"], "vs": {"vp_ratio": 1.8}, "rho": {"gardner": True}})
    config = load_config(write(tmp_path, raw, "elastic.yaml"))
    scene = build_scene(config, plan_scene(config))
    one = run_forward(scene)
    two = pools.forward_on_workers(scene, ParallelConfig(**THREADS))
    for c in ("vx", "vz", "pressure"):
        np.testing.assert_array_equal(getattr(two, c), getattr(one, c))


def test_a_gpu_listed_twice_is_refused(monkeypatch):
    # Warp keeps one current stream and one capture state per GPU: two threads on one GPU would mix them. CI has no
    # GPU: every device resolves as given (cuda -> cuda:0, as Warp resolves it on a one-GPU host).
    from adseismic.solve import common, devices

    monkeypatch.setattr(common, "resolve_device", lambda d: "cuda:0" if d == "cuda" else d)
    par = ParallelConfig(engine="threads", devices=["cuda:0", "cuda:1", "cuda"])
    with pytest.raises(ValueError, match=r"parallel.devices\[2\]: cuda:0 is listed twice; .*list each GPU once"):
        devices.thread_devices(par, "cuda:0", 4)
    assert devices.thread_devices(ParallelConfig(engine="threads", devices=["cpu", "cpu"]), "cpu", 4) == ["cpu", "cpu"]


@pytest.mark.skipif(not wp.get_cuda_device_count(), reason="no CUDA device")
def test_every_gpu_of_this_host_gives_the_gradient_of_one_gpu(tmp_path):
    # the CUDA path: a thread per GPU on its own stream, graphs captured in the threads, kept per device
    problem = Problem(tmp_path, n_shots=2 * wp.get_cuda_device_count() + 1)
    problem.kw["device"] = "cuda:0"
    with DevicePool(ParallelConfig(engine="threads", devices="all"), "cuda:0", problem.n_shots) as pool:
        pool.keep(problem.batches())
        for _ in range(2):  # the second evaluation replays the graphs kept on each GPU
            loss, grad, _ = distributed.reduce_in_order(pool.evaluate(problem.model, problem.params()), problem.model.shape)
    one_loss, one_grad = problem.one_process(per_batch=1, resident=True)
    # float64 on GPUs of one kind: the kernels are the same; the misfit's per-trace sums meet in an atomic add, whose
    # order may differ between runs (a few ulps of the total)
    assert abs(loss - one_loss) <= 1e-12 * abs(one_loss)
    assert np.linalg.norm(grad - one_grad) <= 1e-12 * np.linalg.norm(one_grad)
