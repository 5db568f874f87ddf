"""Shot parallelism on Dask (issue 25, adseismic.solve.distributed): a LocalCluster of 2 CPU workers gives the
gradient and misfit of one process (float64), the same FWI iterates, the fault-free gradient when a worker is
killed during an evaluation, and bad `parallel:` input is refused before work with exit 2."""

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("distributed")

from adseismic.cli import main
from adseismic.config.parallel import ParallelConfig
from adseismic.solve import distributed, residency

from .test_fwi import TINY
from .test_parallel_threads import Problem, assert_fwi_iterates_do_not_depend_on, write

PARALLEL = {"engine": "dask", "scheduler": "local", "devices": ["cpu", "cpu"]}


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    return Problem(tmp_path_factory.mktemp("problem"))


@pytest.fixture(scope="module")
def pool(problem):
    environ = dict(os.environ)
    with distributed.ShotPool(ParallelConfig(devices=["cpu", "cpu"]), "cpu", problem.n_shots) as pool:
        yield pool
    # distributed's nanny leaves OMP/MKL/OPENBLAS_NUM_THREADS=1 in os.environ: later processes would sum with one BLAS
    # thread and differ in the last bit (a kill -9/resume run in a subprocess did); the pool puts them back
    assert dict(os.environ) == environ


def test_two_workers_give_the_gradient_of_one_process(problem, pool):
    assert len(pool.workers()) == 2
    pool.keep(problem.batches())
    rs = pool.evaluate(problem.model, problem.params())
    assert [r["first"] for r in rs] == [0, 1, 2]  # batch order
    assert pool.reruns == 0  # every batch ran through its worker's caller, none as a task
    assert len({r["pid"] for r in rs}) == 2 and os.getpid() not in {r["pid"] for r in rs}  # both workers, not this process
    loss, grad, _ = distributed.reduce_in_order(rs, problem.model.shape)
    one_loss, one_grad = problem.one_process()  # one batch of all shots, misfit on the host: equal to round-off
    assert abs(loss - one_loss) <= 1e-12 * abs(one_loss)
    assert np.linalg.norm(grad - one_grad) <= 1e-12 * np.linalg.norm(one_grad)
    # the same batches in one process as fwi runs them (the data on the device, l2 formed there): bit for bit
    per_shot_loss, per_shot_grad = problem.one_process(per_batch=1, resident=True)
    assert loss == per_shot_loss
    np.testing.assert_array_equal(grad, per_shot_grad)
    for _ in range(2):  # the data stayed on the workers' devices: only the model went out
        again = distributed.reduce_in_order(pool.evaluate(problem.model, problem.params()), problem.model.shape)
        assert again[0] == loss and np.array_equal(again[1], grad)
    # three evaluations, one upload of each batch's observed data and weights per worker that ran it (its own
    # worker; another one too if Dask's work stealing moved a task there)
    ups = pool.client.run(lambda: {at[0]: n for at, n in residency.UPLOADS.items()})
    key = f"{pool.token}-{pool.generation}"
    assert {k for w in ups.values() for k in w} == {f"{key}-{k}" for k in range(3)}, ups
    assert {n for w in ups.values() for n in w.values()} == {1}, ups


def resident_keys(pool) -> dict:
    """{worker pid: its resident batch keys} (solve.residency.RESIDENT of each worker process)."""
    return dict(pool.client.run(lambda: (os.getpid(), sorted(at[0] for at in residency.RESIDENT))).values())


@pytest.mark.parametrize("per_batch", [1, 2], ids=["model broadcast first", "model in each task"])
def test_a_worker_killed_during_an_evaluation_still_gives_the_gradient(problem, pool, per_batch):
    # 3 shots on 2 workers: in 3 batches the model goes to every worker before the tasks, in 2 (one a worker, fwi's
    # default) each task carries it (ShotPool.evaluate); either way the re-run tasks need nothing of the dead worker
    pool.keep(problem.batches(per_batch=per_batch))
    assert not [k for keys in resident_keys(pool).values() for k in keys]  # the previous band's device arrays freed
    clean = distributed.reduce_in_order(pool.evaluate(problem.model, problem.params()), problem.model.shape)
    pids = pool.client.run(os.getpid)  # {worker address: pid}, processes this test's pool started
    victim = max(pids)
    out = {}
    runner = threading.Thread(target=lambda: out.setdefault("rs", pool.evaluate(problem.model, problem.params())))
    runner.start()
    deadline = time.time() + 30
    while victim not in pool.busy() and time.time() < deadline:  # the victim runs batches of this evaluation
        time.sleep(0.002)
    assert victim in pool.busy() and runner.is_alive(), "no batch reached the worker to kill"
    os.kill(pids[victim], signal.SIGKILL)
    runner.join(120)
    assert not runner.is_alive() and "rs" in out
    assert pool.reruns >= 1  # the victim's batches re-ran as tasks
    assert pids[victim] not in {r["pid"] for r in out["rs"]}  # its shots ran elsewhere (or on the restarted worker)
    keys = resident_keys(pool)  # ... which uploaded their data to its device
    assert all(f"{pool.token}-{pool.generation}-{k}" in keys[r["pid"]] for k, r in enumerate(out["rs"])), keys
    loss, grad, _ = distributed.reduce_in_order(out["rs"], problem.model.shape)
    assert loss == clean[0]
    np.testing.assert_array_equal(grad, clean[1])
    again = distributed.reduce_in_order(pool.evaluate(problem.model, problem.params()), problem.model.shape)
    assert pool.reruns == 0 and again[0] == loss  # the next evaluation routed to the callers where the data are now


def test_a_running_scheduler_gives_the_gradient_of_one_process(problem):
    # a scheduler this run did not start (as a dask-jobqueue cluster's): the client reaches the workers only through
    # it, so the callers' calls go by the scheduler; the result is the one-process one
    import logging

    from distributed import LocalCluster

    environ = dict(os.environ)  # (the nanny leaves its workers' thread settings in os.environ; see `pool`)
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0", silence_logs=logging.WARNING)
    try:
        par = ParallelConfig(scheduler=cluster.scheduler_address, workers=2, devices=["cpu"])
        with distributed.ShotPool(par, "cpu", problem.n_shots) as pool:
            pool.keep(problem.batches())
            rs = pool.evaluate(problem.model, problem.params())
            assert pool.reruns == 0 and len(pool.callers) == 2 and not pool.client.direct_to_workers
            loss, grad, _ = distributed.reduce_in_order(rs, problem.model.shape)
    finally:
        cluster.close()
        os.environ.clear()
        os.environ.update(environ)
    one_loss, one_grad = problem.one_process()
    assert abs(loss - one_loss) <= 1e-12 * abs(one_loss)
    assert np.linalg.norm(grad - one_grad) <= 1e-12 * np.linalg.norm(one_grad)


@pytest.mark.slow
def test_fwi_iterates_do_not_depend_on_the_workers(tmp_path):
    assert "2 Dask worker(s)" in assert_fwi_iterates_do_not_depend_on(PARALLEL, tmp_path, rtol=0.0)


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("parallel, key, words", [
    ({"scheduler": f"tcp://127.0.0.1:{free_port()}"}, "parallel.scheduler", ["no Dask scheduler answers", "scheduler: local"]),
    ({"devices": ["cuda:7"]}, "parallel.devices[0]", ["cuda:7", "not available"]),
    ({"devices": ["cpu", "cpu", "cpu", "cpu"]}, "parallel.devices", ["4 devices for 3 shot(s)", "at most 3"]),
    ({"workers": 5}, "parallel.workers", ["5 workers for 3 shot(s)"]),
    ({"engine": "mpi"}, "parallel.engine", ["dask"]),
    ({"scheduler": "my-cluster"}, "parallel.scheduler", ["tcp://"]),
    ({"devices": ["gpu0"]}, "parallel.devices[0]", ["cuda:N"]),
    ({"shedular": "local"}, "parallel.shedular", ["unknown key"]),
])  # fmt: skip
def test_bad_parallel_input_exits_2_before_work(tmp_path, capsys, monkeypatch, parallel, key, words):
    monkeypatch.setattr(distributed, "CONNECT_TIMEOUT", 1.0)
    out = tmp_path / "run"
    assert main(["fwi", str(write(tmp_path, dict(TINY, parallel=parallel))), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert f"error: {key}:" in err, err
    assert all(w in err for w in words), err
    assert not out.exists()


def test_runs_without_dask_when_there_is_no_parallel_section(tmp_path):
    # dask hidden: the package imports, and a parallel section is refused with the install line
    code = ("import sys; sys.modules['distributed'] = None; sys.modules['dask'] = None\n"
            "from adseismic.inversion.fwi import run_fwi; from adseismic.solve import distributed as d\n"
            "from adseismic.config.parallel import ParallelConfig\n"
            "try:\n    d.check_parallel(ParallelConfig(), 'cpu', 3)\nexcept ValueError as e:\n    print(e)\n")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "parallel.engine: dask is not installed" in out.stdout and "adseismic[dask]" in out.stdout
