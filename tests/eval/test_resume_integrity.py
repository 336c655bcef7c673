"""Resume checks what it reuses: missing stage outputs are recomputed, and the result equals an undamaged run's;
changed or added files stop the run with nothing changed (they may be the user's), and once they are moved out
of the folder the run completes as if they had been deleted.

The small real stages of `tests/eval/_tiny_stages.py` write every kind of output the product writes:
16-bit PNG folders, a PLY, a `.pt` checkpoint file (JSON text there; the real checkpoint in the slow
test), JSON, COLMAP binaries and `.npz`. They are deterministic, so a re-run stage writes the bytes it
wrote the first time and the run's final files are compared byte for byte.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from eval.pipeline import preset, run_pipeline
from eval.pipeline.stage import RECORD_DIR, UnownedOutputError
from tests.eval._tiny_stages import TinyStages, make_scene

#: Damaged file (a glob under OUT; the first match) -> the stage that wrote it.
DAMAGE_TARGETS = {
    "round1/denoised/view_003.png": "denoise",        # PNG in an output folder
    "round1/n2v_model.pt": "denoise",                 # .pt
    "round1/align/sparse/0/images.bin": "align",      # COLMAP binary deep in an output folder
    "round1/point_cloud.ply": "splat",                # PLY
    "round2/selection.json": "select",                # JSON
    "round2/renders/*.png": "render",                 # PNG of the last stage
}


def _cfg(**kw):
    # Without the fuse extension unless a test turns it on.
    return dataclasses.replace(preset("fast", views=3, **kw), fuse_noisy_splat=False)


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _random_bytes(path: Path) -> None:
    # Same size: only the content hash can tell.
    size = path.stat().st_size
    path.write_bytes(np.random.default_rng(1).integers(0, 256, size, dtype=np.uint8).tobytes())


DAMAGE = {"truncate": _truncate, "random_bytes": _random_bytes, "delete": Path.unlink}


def _snapshot(out: Path) -> dict[str, bytes | dict]:
    """Every file under `out` by relative path: bytes, except stage records (key and output manifest
    only: they also hold the run's seconds) and the report (it holds this invocation's timings)."""
    snap: dict[str, bytes | dict] = {}
    for p in sorted(out.rglob("*")):
        rel = p.relative_to(out).as_posix()
        if not p.is_file() or p.name in ("report.json", "report.md"):
            continue
        if p.parent.name == RECORD_DIR:
            rec = json.loads(p.read_text())
            snap[rel] = {"key": rec["key"], "manifest": rec["manifest"]}
        else:
            snap[rel] = p.read_bytes()
    return snap


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """(scene folder, finished two-round run) shared by the damage tests; each test works on a copy."""
    root = tmp_path_factory.mktemp("resume")
    scene = make_scene(root / "images", n=5)
    run_pipeline(scene, root / "ref", _cfg(rounds=2), stages=TinyStages().stages())
    return scene, root / "ref"


def _copy(reference, tmp_path) -> Path:
    out = tmp_path / "out"
    shutil.copytree(reference[1], out)
    return out


def test_intact_copy_is_reused_whole(reference, tmp_path):
    out = _copy(reference, tmp_path)
    tiny = TinyStages()
    res = run_pipeline(reference[0], out, _cfg(rounds=2), stages=tiny.stages())
    assert not tiny.calls and all(s.skipped for r in res.rounds for s in r.stages.values())
    # A hidden file in an output folder (e.g. a file manager's) is not an output: still reused.
    (out / "round1" / "renders" / ".DS_Store").write_bytes(b"x")
    run_pipeline(reference[0], out, _cfg(rounds=2), stages=tiny.stages())
    assert not tiny.calls


def _all_bytes(out: Path) -> dict[str, bytes]:
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("damage", sorted(DAMAGE))
@pytest.mark.parametrize("target", sorted(DAMAGE_TARGETS))
def test_damaged_output_is_recomputed(reference, tmp_path, target, damage):
    scene, ref = reference
    out = _copy(reference, tmp_path)
    path = sorted(out.glob(target))[0]
    DAMAGE[damage](path)
    tiny = TinyStages()
    if damage != "delete":
        # A changed file may be the user's edit: the run stops, naming it, before it changes anything.
        before = _all_bytes(out)
        with pytest.raises(UnownedOutputError, match=f"{path.name} \\(changed since the stage wrote it\\)"):
            run_pipeline(scene, out, _cfg(rounds=2), stages=tiny.stages())
        assert not tiny.calls and _all_bytes(out) == before
        path.rename(tmp_path / "kept")  # the fix the error names: move it out of the folder
    res = run_pipeline(scene, out, _cfg(rounds=2), stages=tiny.stages())
    # Only the damaged stage runs: it writes the same bytes again, so the stages after it read exactly
    # what they read before and their checked outputs are reused (see the next test for the case where
    # the re-run writes different bytes).
    assert dict(tiny.calls) == {DAMAGE_TARGETS[target]: 1}
    rnd = int(target[len("round")])
    assert not res.rounds[rnd - 1].stages[DAMAGE_TARGETS[target]].skipped
    assert _snapshot(out) == _snapshot(ref)
    assert not [p for p in out.rglob(".*") if any(t in p.name for t in (".work-", ".old-", ".tmp"))]


def test_extra_file_in_an_output_folder_stops_the_run(reference, tmp_path):
    out = _copy(reference, tmp_path)
    extra = out / "round1" / "denoised" / "view_999.png"
    extra.write_bytes((out / "round1" / "denoised" / "view_000.png").read_bytes())
    tiny = TinyStages()
    with pytest.raises(UnownedOutputError, match="view_999.png \\(not written by the stage\\)") as info:
        run_pipeline(reference[0], out, _cfg(rounds=2), stages=tiny.stages())
    assert "move these files out" in info.value.fix
    assert not tiny.calls and extra.is_file()
    extra.rename(tmp_path / "view_999.png")
    run_pipeline(reference[0], out, _cfg(rounds=2), stages=tiny.stages())
    assert not tiny.calls and _snapshot(out) == _snapshot(reference[1])


def test_changed_rebuild_reruns_every_later_stage_even_after_an_interruption(tmp_path):
    """When the re-run stage writes different bytes (here a checkpoint with a timestamp, as real
    training on a GPU may), every stage after it runs again: their keys hold the upstream outputs'
    digests, so this holds in a later process too, after an interruption between the stages."""
    scene = make_scene(tmp_path / "images", n=5)
    out = tmp_path / "out"
    tiny = TinyStages()
    tiny.stamp_checkpoints = True
    run_pipeline(scene, out, _cfg(rounds=2), stages=tiny.stages())
    (out / "round1" / "denoised" / "view_001.png").unlink()
    interrupted = TinyStages()
    interrupted.stamp_checkpoints = True
    interrupted.fail_next.add("splat")
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(scene, out, _cfg(rounds=2), stages=interrupted.stages())
    assert dict(interrupted.calls) == {"denoise": 1, "align": 1, "splat": 1}
    resumed = TinyStages()
    resumed.stamp_checkpoints = True
    res = run_pipeline(scene, out, _cfg(rounds=2), stages=resumed.stages())
    # denoise and round 1's align are complete and checked; everything after them runs.
    assert dict(resumed.calls) == {"splat": 2, "render": 2, "select": 1, "refine": 1, "align": 1}
    assert res.rounds[0].stages["denoise"].skipped and res.rounds[0].stages["align"].skipped
    again = TinyStages()
    again.stamp_checkpoints = True
    run_pipeline(scene, out, _cfg(rounds=2), stages=again.stages())
    assert not again.calls


def test_damage_with_fuse_stage(tmp_path):
    """The fuse stage's two output folders are checked too; a file missing from `noisy_renders` re-runs fuse
    only."""
    scene = make_scene(tmp_path / "images", n=5)
    cfg = dataclasses.replace(_cfg(rounds=1), fuse_noisy_splat=True)
    run_pipeline(scene, tmp_path / "ref", cfg, stages=TinyStages().stages())
    shutil.copytree(tmp_path / "ref", tmp_path / "out")
    sorted((tmp_path / "out" / "round1" / "noisy_renders").glob("*.png"))[2].unlink()
    tiny = TinyStages()
    run_pipeline(scene, tmp_path / "out", cfg, stages=tiny.stages())
    assert dict(tiny.calls) == {"fuse": 1}
    assert _snapshot(tmp_path / "out") == _snapshot(tmp_path / "ref")


@pytest.mark.slow  # real N2V and splat training (a few steps): ~20 s on a loaded 2-core machine
def test_product_stages_recompute_damaged_outputs(tmp_path):
    """The product's denoise, splat and render stages (alignment from the tiny set): a deleted real
    checkpoint and a deleted PLY are recomputed, and the final Gaussians, renders and checkpoint equal
    the undamaged run's."""
    import torch

    from denoise.model import load_checkpoint
    from eval.pipeline import DenoiseSettings, SplatSettings, product_stages
    from eval.pipeline.views import read_views
    from splat.ply import read_gaussian_ply

    scene = make_scene(tmp_path / "images", n=4, size_wh=(64, 48))
    tiny = TinyStages()
    stages = dataclasses.replace(product_stages(), align=tiny.align)
    cfg = dataclasses.replace(_cfg(rounds=1), denoise=DenoiseSettings(n2v_preset="fast", n2v_steps=4, passes=1),
                              splat=SplatSettings(preset="quick", iters=4))
    ref, out = tmp_path / "ref", tmp_path / "out"
    run_pipeline(scene, ref, cfg, stages=stages)
    shutil.copytree(ref, out)
    (out / "round1" / "n2v_model.pt").unlink()
    (out / "round1" / "point_cloud.ply").unlink()
    res = run_pipeline(scene, out, cfg, stages=stages)
    r1 = res.rounds[0]
    assert not r1.stages["denoise"].skipped and not r1.stages["splat"].skipped
    # Compared as arrays: equal values are what matters to the stages after these, whether or not
    # torch.save/PLY writing repeat their bytes (they do on this CPU path; the snapshot checks that).
    a, b = load_checkpoint(ref / "round1" / "n2v_model.pt"), load_checkpoint(out / "round1" / "n2v_model.pt")
    for (ka, va), (kb, vb) in zip(a.unet.state_dict().items(), b.unet.state_dict().items(), strict=True):
        assert ka == kb and torch.equal(va, vb), ka
    assert (a.mean, a.std, a.history) == (b.mean, b.std, b.history)
    ga, gb = (read_gaussian_ply(o / "round1" / "point_cloud.ply") for o in (ref, out))
    assert torch.equal(ga.means, gb.means)
    ra, rb = read_views(ref / "round1" / "renders"), read_views(out / "round1" / "renders")
    assert ra.keys() == rb.keys() and all(np.array_equal(ra[k], rb[k]) for k in ra)
    assert _snapshot(out) == _snapshot(ref)
