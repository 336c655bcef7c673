"""`denoise-gs eval` / `cost` on Ray (`eval.distributed`): the task graph, rows identical to the serial
path's, no shared stage computed twice, and the refused `--workers` / `--ray-address` values.

The fast tests share one local cluster of 2 CPUs (module fixture). Its workers run the small real
stages of the pipeline tests in place of the product's (installed by the cluster's worker setup, as
`Harness` in test_eval_runs.py does in-process), and every stage call is logged to a file so that
calls in the worker processes can be counted. The real evaluation on Ray is in
test_distributed_real.py: `ray_cluster` runs on a Ray already initialised in the process, which here
would be this module's cluster with those stages and a fake scorer."""

from __future__ import annotations

import collections
import dataclasses
import functools
import math
import os
import socket
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

import eval.evaluate
import eval.methods
from eval.cli import main
from eval.cost import CostConfig, run_cost_sweep
from eval.distributed import (
    ClusterSettings,
    RayExecutor,
    chain_after,
    check_ray_address,
    ray_cluster,
    submission_order,
    warm_slots,
)
from eval.evaluate import EvalConfig, evaluate_dataset, expected_costs, share_keys, task_graph
from eval.pipeline import preset
from eval.pipeline.validate import DatasetFolder
from mvgeo.common.errors import AlignmentRefusedError, InputError
from tests.common.cli_contract import assert_refused
from tests.eval._tiny_stages import TinyStages, make_scene, tiny_dataset

REPO = Path(__file__).resolve().parents[2]
STAGE_NAMES = ("denoise", "align", "splat", "render", "select", "refine", "fuse")


# ----------------------------------------------------------------- the tiny stages, in any process
def _round_folder(work_dir: Path) -> str:
    """The `.../roundN` folder a stage call works in (its work folder is a private one inside)."""
    parts = Path(work_dir).parts
    i = max(k for k, p in enumerate(parts) if p.startswith("round"))
    return str(Path(*parts[:i + 1]))


def _logged(log: Path, name: str, fn, ctx):
    with open(log, "a") as f:  # one short line per O_APPEND write: lines of concurrent workers do not mix
        f.write(f"{name}\t{_round_folder(ctx.work_dir)}\n")
    return fn(ctx)


def logged_stages(log: Path, tiny: TinyStages | None = None):
    """The tiny stages, each call appended to `log` as "stage<TAB>round folder"."""
    stages = (tiny or TinyStages()).stages()
    return dataclasses.replace(stages, **{n: functools.partial(_logged, log, n, getattr(stages, n))
                                          for n in STAGE_NAMES})


def _ply_path(path, device):
    return path


def fake_score_scene(model, gt, est_train, dataset, config, est_cameras=(), renders_out=None):
    """Scores that differ per run folder and per aligned camera rig (seeded), so a row in the wrong
    place or from another run shows."""
    ply = Path(model)
    folder = "/".join(ply.parts[-4:-1])  # <seed>/<method folder>/<round>
    rig = 0.0 if est_train is None else float(sum(np.abs(p).sum() for p in est_train.values()))
    psnr = 20.0 + (zlib.crc32(folder.encode()) % 1000) / 100.0 + len(ply.read_text()) / 1e4
    if renders_out is not None:
        renders_out.update({n: np.full((40, 48, 3), 0.5, np.float32) for n in dataset.test})
    return {n: {"psnr_db": psnr, "ssim": 0.5, "lpips": 0.3} for n in dataset.test}, \
        {"rot_err_deg": rig, "ate": 0.1}


def install_tiny(log: Path, setattr_=setattr) -> None:
    """Tiny stages and the fake scorer in place of the product's (in a worker: at its start)."""
    setattr_(eval.methods, "product_stages", functools.partial(logged_stages, log))
    setattr_(eval.evaluate, "read_gaussian_ply", _ply_path)
    setattr_(eval.evaluate, "_score_scene", fake_score_scene)


def cost_score(run_dir, dataset, names):
    return {"psnr_db": 20.0 + len(names) + len(run_dir.parent.name) / 100, "ssim": 0.5, "lpips": 0.3,
            "rot_err_deg": 1.0, "ate": 0.1}


def _calls(log: Path, out: Path) -> collections.Counter:
    """(stage, round folder relative to `out`) -> calls."""
    lines = log.read_text().splitlines() if log.is_file() else []
    rows = [ln.split("\t") for ln in lines]
    return collections.Counter((s, str(Path(f).relative_to(out))) for s, f in rows if Path(f).is_relative_to(out))


# ----------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A local Ray cluster of 2 CPUs whose workers run the tiny stages; yields (executor, stage log)."""
    log = tmp_path_factory.mktemp("ray") / "stage_calls.log"
    with pytest.MonkeyPatch.context() as mp:
        # The workers import this module (the setup hook, the task functions): the repository on their path.
        mp.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
        with ray_cluster(ClusterSettings(workers=2), worker_setup=functools.partial(install_tiny, log)) as ex:
            yield ex, log


@pytest.fixture()
def dataset(tmp_path) -> DatasetFolder:
    return tiny_dataset(tmp_path / "data")


# ----------------------------------------------------------------- the task graph
def test_chain_after_waits_for_the_previous_unit_of_a_key():
    assert chain_after([(k,) for k in "abacab"]) == [(), (), (0,), (), (2,), (1,)]
    assert chain_after([]) == []
    # a unit with two keys waits for the last unit of each, and is then the last of both
    assert chain_after([("a",), ("b",), ("a", "b"), ("a",), ("b",), ()]) == [(), (), (0, 1), (2,), (2,), ()]


def test_share_keys_chain_a_family_the_ablations_and_the_gt_pose_variants(tmp_path, dataset):
    cfg = EvalConfig(methods=("instantsplat",), seeds=1, preset="fast")
    tasks = [eval.evaluate.EvalTask("s", eval.methods.METHODS[m], seed, dataset, preset("fast"), tmp_path, tmp_path,
                                    cfg)
             for seed in (0, 1) for m in ("instantsplat", "n2v_round1", "denoise_gs", "ablate_no_selection",
                                          "oracle_clean", "n2v_round1@gt_poses")]
    after = chain_after([share_keys(t) for t in tasks])
    # seed 0: instantsplat alone; n2v_round1 -> denoise_gs -> ablate_no_selection; the variant after the last
    # of its method's folder and after oracle_clean (its points); seed 1 likewise, apart.
    assert after == [(), (), (1,), (2,), (), (3, 4), (), (), (7,), (8,), (), (9, 10)]


def _chain_after_by_scan(writes, reads):
    """Reference: unit i waits for unit j < i when j writes a key i writes or reads, or j reads a key i
    writes, and no unit between them writes that key (each pair judged on its own, by scanning)."""
    after = []
    for i in range(len(writes)):
        deps = set()
        for j in range(i):
            for x in {*writes[i], *reads[i]}:
                j_writes, j_reads = x in writes[j], x in reads[j] and x not in writes[j]
                i_writes = x in writes[i]
                if not (j_writes or (j_reads and i_writes)):
                    continue
                if not any(x in writes[k] for k in range(j + 1, i)):
                    deps.add(j)
        after.append(tuple(sorted(deps)))
    return after


def test_chain_after_lets_the_readers_of_a_key_run_side_by_side():
    # w: writes a, then three readers of a, then a writer of a waits for all three, then a reader for it
    writes = [("a",), (), (), ("b",), ("a",), ()]
    reads = [(), ("a",), ("a",), ("a",), (), ("a", "b")]
    assert chain_after(writes, reads) == [(), (0,), (0,), (0,), (0, 1, 2, 3), (3, 4)]
    # a key both written and read counts as written: the next reader waits for it
    assert chain_after([("a",), ("a",), ()], [(), ("a",), ("a",)]) == [(), (0,), (1,)]
    with pytest.raises(ValueError, match="reads has 1 entries for 2 units"):
        chain_after([(), ()], [()])
    # against the pairwise scan, on random graphs of 4 keys
    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(1, 9))
        writes = [tuple(k for k in "abcd" if rng.random() < 0.3) for _ in range(n)]
        reads = [tuple(k for k in "abcd" if rng.random() < 0.3) for _ in range(n)]
        assert chain_after(writes, reads) == _chain_after_by_scan(writes, reads)
        assert chain_after(writes) == _chain_after_by_scan(writes, [()] * n)


def test_task_graph_runs_the_gt_pose_variants_side_by_side(tmp_path, dataset):
    cfg = EvalConfig(methods=("instantsplat",), seeds=1, preset="fast")
    names = ("instantsplat", "oracle_clean", "instantsplat@gt_poses", "oracle_clean@gt_poses", "n2v_round1@gt_poses")
    tasks = [eval.evaluate.EvalTask("s", eval.methods.METHODS[m], seed, dataset, preset("fast"), tmp_path, tmp_path,
                                    cfg)
             for seed in (0, 1) for m in names]
    # the variants read the runs before them (instantsplat, oracle_clean) and wait only for those; the
    # n2v_round1 variant runs n2v_round1 itself (no earlier task does) and only reads oracle_clean's points
    assert task_graph(tasks) == [(), (), (0, 1), (1,), (1,), (), (), (5, 6), (6,), (6,)]
    # where every key was written, as before: one chain through oracle_clean's folder
    assert chain_after([share_keys(t) for t in tasks])[:5] == [(), (), (0, 1), (2,), (3,)]
    # without the methods they need: oracle_clean's variant runs it as its own method, and the variant after
    # it reads it; instantsplat's variant before it also runs oracle_clean (for its points), but only after
    # instantsplat, which may fail first: so oracle_clean's variant still writes, after it
    alone = [t for t in tasks if "@" in t.method.name and t.seed == 0]
    assert [t.method.name for t in alone] == ["instantsplat@gt_poses", "oracle_clean@gt_poses", "n2v_round1@gt_poses"]
    assert task_graph(alone) == [(), (0,), (1,)]
    names = ("instantsplat@gt_poses", "product@gt_poses", "n2v_round1@gt_poses")
    variants = [eval.evaluate.EvalTask("s", eval.methods.METHODS[m], 0, dataset, preset("fast"), tmp_path, tmp_path,
                                       cfg) for m in names]
    assert task_graph(variants) == [(), (0,), (1,)]  # oracle_clean's folder written by each in turn


def _levels_by_paths(after, cost):
    """Reference: each unit's level as the costliest path of waiting units from it, every path enumerated."""
    waiting = collections.defaultdict(list)
    for i, deps in enumerate(after):
        for d in deps:
            waiting[d].append(i)

    def longest(i):
        return cost[i] + max((longest(j) for j in waiting[i]), default=0.0)

    return [longest(i) for i in range(len(after))]


def _makespan(order, after, cost, workers):
    """List scheduling by hand: `workers` take the first unit of `order` whose waits are over, whenever free."""
    end, free, left = {}, [0.0] * workers, list(order)
    while left:
        w = min(range(workers), key=lambda k: free[k])
        ready = [i for i in left if all(d in end for d in after[i])]
        i = ready[0]
        start = max([free[w], *(end[d] for d in after[i])])
        end[i] = free[w] = start + cost[i]
        left.remove(i)
    return max(end.values())


def test_submission_order_takes_the_longest_remaining_chain_first():
    # two short and two long independent runs in the serial order (oracle, n2v, oracle, n2v): the long
    # ones first, so on two workers they run side by side and the short ones fill in after them
    after, cost = [(), (), (), ()], [1.0, 2.5, 1.0, 2.5]
    order = submission_order(after, cost)
    assert order == [1, 3, 0, 2]
    assert _makespan(order, after, cost, 2) == 3.5 < _makespan(range(4), after, cost, 2) == 4.5
    # a chain's head carries the chain: a (1) then its variant (1.2) outranks a lone run of 2
    assert submission_order([(), (0,), ()], [1.0, 1.2, 2.0]) == [0, 2, 1]
    assert submission_order([], []) == []
    with pytest.raises(ValueError, match="positive"):
        submission_order([()], [0.0])
    with pytest.raises(ValueError, match="positive"):
        submission_order([()], [math.nan])
    with pytest.raises(ValueError, match="earlier units"):
        submission_order([(1,), ()], [1.0, 1.0])


def test_submission_order_matches_the_levels_of_every_path():
    rng = np.random.default_rng(3)
    for _ in range(50):
        n = int(rng.integers(1, 9))
        after = [tuple(sorted({int(d) for d in rng.integers(0, i, size=rng.integers(0, 3))})) if i else ()
                 for i in range(n)]
        cost = [float(c) for c in rng.uniform(0.1, 3.0, n)]
        order = submission_order(after, cost)
        assert sorted(order) == list(range(n))
        position = {u: k for k, u in enumerate(order)}
        assert all(position[d] < position[i] for i, deps in enumerate(after) for d in deps)
        levels = _levels_by_paths(after, cost)
        assert [levels[u] for u in order] == sorted(levels, reverse=True)


def test_expected_costs_count_what_an_earlier_run_has_not_done(tmp_path, dataset):
    cfg = EvalConfig(methods=("instantsplat",), seeds=1, preset="fast")
    names = ("instantsplat", "n2v_round1", "denoise_gs", "ablate_no_selection", "oracle_clean", "n2v_round1@gt_poses",
             "product@gt_poses", "product")
    base = preset("fast", rounds=2)
    tasks = [eval.evaluate.EvalTask("s", eval.methods.METHODS[m], 0, dataset, base, tmp_path, tmp_path, cfg)
             for m in names]
    r, d, g, s = (eval.evaluate.ROUND_COST, eval.evaluate.LEARNED_DENOISER_COST, eval.evaluate.GT_SPLAT_COST,
                  eval.evaluate.SCORING_COST)
    assert expected_costs(tasks) == pytest.approx([
        s + r,                  # instantsplat: one round, no denoiser to train
        s + r + d,              # n2v_round1: one round with the denoiser
        s + r + d,              # denoise_gs: its second round in the same folder
        s + r + d,              # ablate_no_selection: round 2 only, round 1 linked in
        s + r,                  # oracle_clean
        s + g,                  # n2v_round1@gt_poses: its method and its points' ran before it
        s + g + 2 * (r + d),    # product@gt_poses: runs the product first (here: two rounds)
        s,                      # product: done by the variant before it
    ])


def rendezvous(item):
    """(name, start, end, met): "wait" waits (up to 120 s) for the file `flag` that "signal" writes, so
    it ends only if both ran at once; "fail" raises; anything else returns at once. "signal" reports the
    time just before it writes the flag (taken after, another process could see the flag and end first)."""
    name, action, flag = item
    start = time.time()
    met = None
    if action == "fail":
        raise KeyError(f"no action for {name}")
    if action == "signal":  # its end is taken before the flag exists: "wait" can only see it later
        end = time.time()
        Path(flag).write_text(name)
        return name, start, end, met
    if action == "wait":
        while not (met := Path(flag).is_file()) and time.time() - start < 120:
            time.sleep(0.05)
    return name, start, time.time(), met


def test_executor_keeps_the_order_and_the_graph(cluster, tmp_path):
    ex, _ = cluster
    flag = str(tmp_path / "flag")
    items = [("a", "wait", flag), ("b", "", flag), ("c", "signal", flag)]
    seen = []
    res = ex.run(rendezvous, items, after=[(), (0,), ()], on_done=lambda d: seen.append(sorted(d)))
    assert [r[0] for r in res] == ["a", "b", "c"]  # the input order, not the finishing order
    (_, _, a_end, a_met), (_, b_start, _, _), (_, _, c_end, _) = res
    assert a_met  # c ran while a was running: the two CPUs were used at once
    assert c_end <= a_end
    assert b_start >= a_end  # b waited for a
    assert [len(d) for d in seen] == [1, 2, 3] and seen[-1] == [0, 1, 2]  # after each finished task
    with pytest.raises(ValueError, match="earlier units"):
        ex.run(rendezvous, items, after=[(1,), (), ()])


def started(item):
    """(name, start time) after sleeping `item`'s seconds."""
    name, seconds = item
    start = time.time()
    time.sleep(seconds)
    return name, start


def test_executor_starts_the_costliest_units_first(cluster):
    ex, _ = cluster
    items = [("short0", 2.0), ("short1", 2.0), ("long0", 2.0), ("long1", 2.0)]
    res = ex.run(started, items, cost=[1.0, 1.0, 5.0, 5.0])
    assert [r[0] for r in res] == ["short0", "short1", "long0", "long1"]  # the input order
    start = dict(res)
    # two CPUs: the two long ones start first, the short ones only when a CPU is free (two seconds later; the
    # margin absorbs a slow worker on a loaded machine); in the input order short0 and short1 would go first
    assert max(start["long0"], start["long1"]) < min(start["short0"], start["short1"])
    with pytest.raises(ValueError, match="cost has 1 entries"):
        ex.run(started, items, cost=[1.0])


def thread_counts(item):
    """(torch threads, OpenCV threads) inside a task."""
    import torch

    from mvgeo.common.deps import cv2

    return torch.get_num_threads(), cv2.getNumThreads()


def test_tasks_run_with_their_cpus_or_the_given_threads(cluster):
    ex, _ = cluster
    assert ex.run(thread_counts, [0, 1]) == [(1, 1), (1, 1)]  # one CPU per task: one thread
    three = RayExecutor(dataclasses.replace(ex.settings, task_threads=3))
    assert three.run(thread_counts, [0]) == [(3, 3)]


def niceness(item):
    """The task's process niceness."""
    return os.nice(0)


def test_tasks_run_at_the_drivers_niceness(cluster):
    """Ray starts its workers at niceness 15, where any other process on the node starves them; a local
    cluster's run at the driver's, as the serial path's work does."""
    ex, _ = cluster
    assert ex.run(niceness, [0, 1]) == [os.nice(0)] * 2


NICENESS_PROBE = """
import os
from eval.distributed import ClusterSettings, ray_cluster

def niceness(_item):
    return os.nice(0)

with ray_cluster(ClusterSettings(workers=2)) as ex:
    print(os.nice(0), *ex.run(niceness, [0, 1]))
"""


def test_a_niced_command_runs_its_workers_at_its_niceness():
    """Ray adds its `worker_niceness` to the niceness of the raylet, which inherits the driver's: a command run
    under `nice -n 3` (from a shell at 0) had its workers at 6, under `nice -n 10` at 19."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run([sys.executable, "-c", NICENESS_PROBE], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300, preexec_fn=lambda: os.nice(3))
    assert done.returncode == 0, done.stderr[-2000:]
    driver, *workers = map(int, done.stdout.split())
    assert driver == min(19, os.nice(0) + 3)
    assert workers == [driver, driver]


def test_executor_raises_a_task_error_as_its_own_type(cluster):
    ex, _ = cluster
    with pytest.raises(KeyError, match="no action for b"):
        ex.run(rendezvous, [("a", "", ""), ("b", "fail", ""), ("c", "", "")])


def refuse(item):
    raise AlignmentRefusedError("the focal length is not determined", kind="focal", views=(item,), fix="add photos")


def test_executor_raises_an_alignment_refusal_as_itself(cluster):
    """`denoise-gs cost` turns a refusal into its own fix (`_rendered_views_refusal`): on Ray it must reach the
    driver as the `AlignmentRefusedError` the serial path gets, not as Ray's `UnserializableException`."""
    ex, _ = cluster
    with pytest.raises(AlignmentRefusedError, match="not determined") as err:
        ex.run(refuse, ["v1"])
    assert (err.value.kind, err.value.views, err.value.fix) == ("focal", ("v1",), "add photos")


PROBE = "tests.eval._warm_probe"


def probe_seen(_item):
    """(worker process id, whether the warm-up's module is imported in it)."""
    import sys

    return os.getpid(), PROBE in sys.modules


def test_started_workers_import_the_preload_and_run_the_tasks(cluster):
    """The module's workers exist already (earlier tests): this checks that the warm-up runs in the
    processes the runs then use and imports there; starting fresh processes is Ray's part."""
    import ray

    ex, _ = cluster
    assert ex.start_workers(0, (PROBE,)) == []
    before = ex.run(probe_seen, range(4))
    assert not any(imported for _, imported in before)  # nothing imported the probe yet
    warm = set(ray.get(ex.start_workers(2, (PROBE,))))
    seen = ex.run(probe_seen, range(6))
    assert {pid for pid, _ in seen} & warm  # the tasks run in the processes the warm-up ran in
    assert all(imported for pid, imported in seen if pid in warm)  # which imported the preload
    failed = ex.start_workers(1, ("tests.eval._no_such_module",))
    assert ex.run(probe_seen, [0])[0][0] > 0  # a failed warm-up is not waited for: the runs go on
    with pytest.raises(ModuleNotFoundError):  # (its own error, had anyone asked)
        ray.get(failed)


@pytest.mark.parametrize("resources, settings, tasks, slots", [
    ({"CPU": 5.0}, ClusterSettings(workers=2, cpus_per_task=2), None, 2),
    ({"CPU": 5.0}, ClusterSettings(workers=2, cpus_per_task=2), 1, 1),  # no more than the runs
    ({"CPU": 64.0, "GPU": 4.0}, ClusterSettings(address="h:1", gpus_per_task=1.0), None, 4),  # GPUs decide
    ({"CPU": 3.0, "GPU": 1.0}, ClusterSettings(workers=3, gpus_per_task=1 / 3), None, 3),  # shared GPU
    ({"CPU": 2.0}, ClusterSettings(workers=2, gpus_per_task=0.5), None, 0),  # GPU tasks, no GPU
])
def test_warm_slots_counts_the_tasks_the_cluster_runs_at_once(resources, settings, tasks, slots):
    assert warm_slots(resources, settings, tasks) == slots


def test_the_cli_preloads_modules_that_exist():
    import importlib

    from eval.cli import COST_PRELOAD, EVAL_PRELOAD

    for name in EVAL_PRELOAD + COST_PRELOAD:
        assert importlib.import_module(name).__name__ == name


# ----------------------------------------------------------------- eval and cost: Ray vs serial
def test_eval_on_ray_gives_the_serial_rows(cluster, dataset, tmp_path, monkeypatch):
    ex, log = cluster
    config = EvalConfig(methods=("3dgs_gt_poses", "instantsplat", "n2v_round1", "denoise_gs", "ablate_no_selection"),
                        seeds=2, preset="fast")
    serial_log = tmp_path / "serial_calls.log"
    install_tiny(serial_log, monkeypatch.setattr)
    serial_out, ray_out = tmp_path / "serial", tmp_path / "ray"
    serial = evaluate_dataset(dataset, serial_out, config, scene="s")
    partial = []
    rows = evaluate_dataset(dataset, ray_out, config, scene="s", executor=ex,
                            on_row=lambda rs: partial.append([(r.method, r.seed) for r in rs]))
    order = [(r.method, r.seed) for r in serial]
    assert order == [(m, s) for s in (0, 1) for m in config.methods]
    assert [(r.method, r.seed) for r in rows] == order
    # Identical rows but for the stages' measured wall seconds.
    strip = [dataclasses.replace(r, seconds=0.0) for r in rows]
    assert strip == [dataclasses.replace(r, seconds=0.0) for r in serial]
    assert all(not r.error and math.isfinite(r.psnr_db) for r in rows)
    assert len({r.psnr_db for r in rows}) == len(rows)  # every run scored apart: a swap would show
    assert len(partial) == len(rows) and partial[-1] == order
    assert all(p == [o for o in order if o in p] for p in partial)  # in the serial order at every step
    # The same stage calls in the same round folders, none twice: shared round 1s were reused.
    ray_calls, serial_calls = _calls(log, ray_out), _calls(serial_log, serial_out)
    assert ray_calls == serial_calls and set(ray_calls.values()) == {1}
    assert ray_calls[("denoise", "runs/s/seed0/n2v/round1")] == 1
    assert ("denoise", "runs/s/seed0/ablate_no_selection/round1") not in ray_calls  # linked from n2v
    assert ("refine", "runs/s/seed1/ablate_no_selection/round2") in ray_calls


def test_gt_pose_variants_on_ray_read_the_runs_before_them(cluster, dataset, tmp_path, monkeypatch):
    """The variants read instantsplat's and oracle_clean's finished runs side by side (`task_graph`), taking
    the run folders' locks in turn: the serial rows, and every stage computed once."""
    ex, log = cluster
    config = EvalConfig(methods=("instantsplat", "oracle_clean", "instantsplat@gt_poses", "oracle_clean@gt_poses",
                                 "n2v_round1@gt_poses"), seeds=1, preset="fast")
    serial_log = tmp_path / "serial_calls.log"
    install_tiny(serial_log, monkeypatch.setattr)
    serial_out, ray_out = tmp_path / "serial", tmp_path / "ray"
    serial = evaluate_dataset(dataset, serial_out, config, scene="s")
    rows = evaluate_dataset(dataset, ray_out, config, scene="s", executor=ex)
    assert [r.method for r in rows] == [m.name for m in config.selected()]  # the registry's order
    assert all(not r.error and math.isfinite(r.psnr_db) for r in rows)
    assert [dataclasses.replace(r, seconds=0.0) for r in rows] == [dataclasses.replace(r, seconds=0.0)
                                                                    for r in serial]
    ray_calls, serial_calls = _calls(log, ray_out), _calls(serial_log, serial_out)
    assert ray_calls == serial_calls and set(ray_calls.values()) == {1}
    assert ray_calls[("splat", "runs/s/seed0/oracle_clean@gt_poses/round1")] == 1


def test_cost_sweep_on_ray_gives_the_serial_rows(cluster, dataset, tmp_path):
    ex, _ = cluster
    cfg = CostConfig(base=preset("fast", rounds=1, views=3),
                     grid={"splat_iters": (7,), "passes": (1,), "train_views": (3, 3)})
    serial_log, ray_log = tmp_path / "serial.log", tmp_path / "ray.log"
    serial = run_cost_sweep(dataset, tmp_path / "serial", cfg, score=cost_score,
                            stages=logged_stages(serial_log))
    rows = run_cost_sweep(dataset, tmp_path / "ray", cfg, score=cost_score, stages=logged_stages(ray_log),
                          executor=ex)
    assert [r.name for r in rows] == ["base", "splat_iters=7", "passes=1", "train_views=3", "train_views=3"]

    def strip(r):
        return dataclasses.replace(r, stage_s=dict.fromkeys(r.stage_s, 0.0), total_s=0.0)

    assert [strip(r) for r in rows] == [strip(r) for r in serial]
    # Points linked to the base point's stages waited for it (splat_iters re-ran the splat and what
    # follows it, not denoise or align); the repeated point waited for its first run and recomputed nothing.
    ray_calls = _calls(ray_log, tmp_path / "ray")
    assert ray_calls == _calls(serial_log, tmp_path / "serial") and set(ray_calls.values()) == {1}
    rerun = {s for s, f in ray_calls if f == "points/splat_iters=7/round1"}
    assert "splat" in rerun and not rerun & {"denoise", "align"}


def test_an_output_folder_error_in_a_ray_task_reaches_the_driver_as_its_own_type(cluster, dataset, tmp_path):
    """A file in a run folder that the evaluation did not write stops the evaluation on Ray as in the
    serial path (an `UnownedOutputError`, exit code 2), not as a "failed" row nor an unpicklable error."""
    from eval.evaluate import EvalTask, copy_train_inputs, run_task
    from eval.methods import METHODS
    from eval.pipeline.stage import UnownedOutputError

    ex, _ = cluster
    out = tmp_path / "out"
    config = EvalConfig(methods=("instantsplat",), seeds=1, preset="fast")
    task = EvalTask("s", METHODS["instantsplat"], 0, dataset, preset("fast", views=3),
                    copy_train_inputs(dataset, out / "inputs" / "s"), out, config)
    (row,) = ex.run(run_task, [task])
    assert not row.error
    notes = out / "runs" / "s" / "seed0" / "instantsplat" / "round1" / "renders" / "notes.txt"
    notes.write_text("mine")
    with pytest.raises(UnownedOutputError, match="notes.txt"):
        ex.run(run_task, [task])
    assert notes.read_text() == "mine"


# ----------------------------------------------------------------- refused values
def _closed_port() -> int:
    """A loopback port nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_cluster_settings_refuse_bad_values():
    with pytest.raises(InputError, match="at least 1"):
        ClusterSettings(workers=0)
    with pytest.raises(InputError, match="--task-threads"):
        ClusterSettings(workers=2, task_threads=0)
    with pytest.raises(InputError, match="alternatives"):
        ClusterSettings(workers=2, address="auto")
    assert not ClusterSettings().distributed and ClusterSettings(workers=2).distributed
    assert ClusterSettings(address="auto").distributed


@pytest.mark.parametrize(("address", "message"), [("ray://127.0.0.1:10001", "ray\\[client\\]"),
                                                  ("127.0.0.1", "not host:port"), ("a b:1", "not host:port"),
                                                  ("127.0.0.1:70000", "not host:port"),
                                                  ("CLOSED", "no Ray head answers")])
def test_check_ray_address_refuses(address, message):
    address = address.replace("CLOSED", f"127.0.0.1:{_closed_port()}")
    start = time.perf_counter()
    with pytest.raises(InputError, match=message):
        check_ray_address(address)
    assert time.perf_counter() - start < 5.0


@pytest.mark.parametrize("command", ["eval", "cost"])
@pytest.mark.parametrize(("extra", "message"), [
    (["--workers", "0"], ["--workers"]),
    (["--workers", "two"], ["--workers"]),
    (["--ray-address", "CLOSED"], ["--ray-address", "no Ray head answers"]),
    (["--ray-address", "ray://127.0.0.1:10001"], ["ray[client]"]),
    (["--workers", "2", "--ray-address", "auto"], ["alternatives"]),
    (["--workers", "2", "--task-threads", "0"], ["--task-threads"]),
    (["--task-threads", "2"], ["--task-threads applies to runs on Ray"]),
])
def test_cli_refuses_bad_cluster_options(tmp_path, capsys, command, extra, message):
    images = make_scene(tmp_path / "data" / "images", n=4)
    extra = [a.replace("CLOSED", f"127.0.0.1:{_closed_port()}") for a in extra]
    assert_refused(main, [command, "llff_like", "--out", tmp_path / "O", *extra], capsys, inputs=[images],
                   watch=[tmp_path], message=message)
