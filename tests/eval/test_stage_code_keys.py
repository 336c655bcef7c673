"""Stage keys cover the code each stage runs (`eval.pipeline.stage`'s rule): its function's module and
the modules/packages it names, `eval.pipeline` and the component packages for the product's stages."""

from __future__ import annotations

import ast
import dataclasses
import hashlib
import importlib
import json
import shutil
import sys
import uuid
from pathlib import Path

import pytest

from eval.pipeline import PipelineStages, preset, product_stages, run_pipeline
from eval.pipeline.hashing import source_digest
from eval.pipeline.stage import code_digests
from eval.pipeline.stages import STAGE_CODE
from mvgeo.common.errors import DgsError
from tests.eval._tiny_stages import TinyStages, make_scene

REPO = Path(__file__).resolve().parents[2]
PROJECT_PACKAGES = ("mvgeo", "splat", "denoise", "data_synth", "eval")

_FUSE_MODULE = '''"""A fuse stage in a module of its own, written by the test."""

from eval.pipeline.views import read_views, write_views

WEIGHT = 0.5


def fuse(ctx):
    denoised = read_views(ctx.inputs["images"])
    noisy = read_views(ctx.inputs["noisy"], list(denoised))
    write_views(ctx.work_dir / "noisy_renders", noisy)
    write_views(ctx.work_dir / "fused", {k: (1 - WEIGHT) * denoised[k] + WEIGHT * noisy[k] for k in denoised})
    return {"weight": WEIGHT}
'''


@pytest.fixture()
def fresh_digests():
    """Each `source_digest` computed afresh, as in a new process (the digests are cached per process)."""
    source_digest.cache_clear()
    yield source_digest.cache_clear
    source_digest.cache_clear()


def _ran(res) -> set[str]:
    return {f"round{r.index}/{name}" for r in res.rounds for name, s in r.stages.items() if not s.skipped}


def _fuse_cfg():
    return dataclasses.replace(preset("fast", views=3, rounds=1), fuse_noisy_splat=True)


def test_changed_constant_reruns_its_stage_and_the_stages_after(tmp_path, monkeypatch, fresh_digests):
    monkeypatch.setattr(sys, "dont_write_bytecode", True)  # no .pyc that could outlive the edit
    name = f"dgs_test_fuse_{uuid.uuid4().hex[:8]}"
    code = tmp_path / "code"
    code.mkdir()
    (code / f"{name}.py").write_text(_FUSE_MODULE)
    monkeypatch.syspath_prepend(str(code))
    monkeypatch.setitem(sys.modules, name, None)  # so that the module is removed after the test
    del sys.modules[name]
    module = importlib.import_module(name)
    scene, out = make_scene(tmp_path / "images", n=4), tmp_path / "out"

    def run():
        return run_pipeline(scene, out, _fuse_cfg(), stages=dataclasses.replace(TinyStages().stages(),
                                                                               fuse=module.fuse))

    assert _ran(run()) == {"round1/denoise", "round1/align", "round1/fuse", "round1/splat", "round1/render"}
    fused_before = (out / "round1" / "fused" / "view_001.png").read_bytes()
    record = json.loads((out / "round1" / "stages" / "fuse.json").read_text())
    assert set(record["code"]) == {name}  # the tiny stages declare no other code
    # Re-importing unchanged code in a new process changes nothing.
    importlib.reload(module)
    fresh_digests()
    assert _ran(run()) == set()
    # The constant changes: the fuse stage and every stage after it run; the ones before are reused.
    (code / f"{name}.py").write_text(_FUSE_MODULE.replace("WEIGHT = 0.5", "WEIGHT = 0.75"))
    importlib.invalidate_caches()
    importlib.reload(module)
    fresh_digests()
    assert module.WEIGHT == 0.75
    assert _ran(run()) == {"round1/fuse", "round1/splat", "round1/render"}
    assert (out / "round1" / "fused" / "view_001.png").read_bytes() != fused_before


def test_product_code_table_enters_the_keys(tmp_path, monkeypatch, fresh_digests):
    """With the product's code table, an edit in a component package re-runs the stages that run it
    and the stages after them; an edit in `eval.pipeline` re-runs every stage."""
    import eval.pipeline.stage as stage_mod

    scene, out = make_scene(tmp_path / "images", n=4), tmp_path / "out"
    edited: set[str] = set()
    real = stage_mod.source_digest
    monkeypatch.setattr(stage_mod, "source_digest", lambda n: "edited" + n if n in edited else real(n))

    def run():
        return run_pipeline(scene, out, _fuse_cfg(),
                            stages=dataclasses.replace(TinyStages().stages(), code=STAGE_CODE))

    run()
    record = json.loads((out / "round1" / "stages" / "splat.json").read_text())
    assert {"eval.pipeline", "splat", "denoise", "mvgeo"} <= set(record["code"])
    assert record["code"]["eval.pipeline"] == source_digest("eval.pipeline")
    edited.add("splat")
    assert _ran(run()) == {"round1/fuse", "round1/splat", "round1/render"}
    edited.add("eval.pipeline")
    assert _ran(run()) == {"round1/denoise", "round1/align", "round1/fuse", "round1/splat", "round1/render"}
    assert _ran(run()) == set()


def test_fuse_weight_is_in_the_fuse_stage_key(tmp_path, monkeypatch, fresh_digests):
    """`FUSE_WEIGHT` lives in `eval/pipeline/fuse_stage.py`: the package digest the product's fuse stage
    carries changes with it (checked on a copy of the package, importable under another name)."""
    digests = code_digests(product_stages().fuse, STAGE_CODE["fuse"])
    assert {"eval.pipeline", "eval.pipeline.fuse_stage"} <= set(digests)
    name = f"dgs_test_pipeline_{uuid.uuid4().hex[:8]}"
    copy = tmp_path / name
    shutil.copytree(REPO / "eval" / "pipeline", copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.syspath_prepend(str(tmp_path))
    before = source_digest(name)
    (copy / "notes.txt").write_text("not source")
    (copy / "__pycache__").mkdir()
    (copy / "__pycache__" / "fuse_stage.cpython-312.pyc").write_bytes(b"\0")
    fresh_digests()
    assert source_digest(name) == before
    text = (copy / "fuse_stage.py").read_text()
    assert text.count("\nFUSE_WEIGHT = 0.5\n") == 1
    (copy / "fuse_stage.py").write_text(text.replace("\nFUSE_WEIGHT = 0.5\n", "\nFUSE_WEIGHT = 0.6\n"))
    fresh_digests()
    assert source_digest(name) != before


def test_source_digest_reference(tmp_path, monkeypatch, fresh_digests):
    # A module is its file's sha256.
    path = REPO / "eval" / "pipeline" / "stages.py"
    assert source_digest("eval.pipeline.stages") == hashlib.sha256(path.read_bytes()).hexdigest()
    # A package: every source file below it, by relative name (a nested change counts).
    pkg = tmp_path / "dgs_test_pkg_digest"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "kernel.cpp").write_text("int f() { return 1; }\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    before = source_digest(pkg.name)
    (pkg / "sub" / "kernel.cpp").write_text("int f() { return 2; }\n")
    fresh_digests()
    assert source_digest(pkg.name) != before
    with pytest.raises(DgsError, match="no_such_module_here"):
        source_digest("no_such_module_here")


def _imported_project_packages(package: str) -> set[str]:
    """Top-level project packages imported anywhere in `package`'s sources (lazy imports included)."""
    found: set[str] = set()
    for f in (REPO / package.replace(".", "/")).rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text(), filename=str(f))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module] if isinstance(node, ast.ImportFrom) and node.module and not node.level else []
            found |= {n.split(".")[0] for n in names} & set(PROJECT_PACKAGES)
    return found


def test_stage_code_table_is_complete():
    """Every product stage has an entry, and the component packages each lists bring along the
    project packages they import (e.g. `splat` imports `denoise.losses`)."""
    product = product_stages()
    fields = {f.name for f in dataclasses.fields(PipelineStages)} - {"code", "denoise_outputs", "denoise_inputs"}
    assert set(product.code) == fields and product.code.items() >= STAGE_CODE.items()
    for stage, code in product.code.items():
        assert "eval.pipeline" in code, stage
        for package in code:
            if package != "eval.pipeline":
                missing = _imported_project_packages(package) - {p.split(".")[0] for p in code}
                assert not missing, (stage, package, missing)
        assert all(len(d) == 64 for d in code_digests(getattr(product, stage), code).values())


def _imported_project_modules(module: str) -> set[str]:
    """Project modules `module`'s source imports (lazy imports included), and those of the `eval` modules outside
    `eval.pipeline` among them, recursively."""
    found: set[str] = set()
    todo = [module]
    while todo:
        f = REPO / (todo.pop().replace(".", "/") + ".py")
        for node in ast.walk(ast.parse(f.read_text(), filename=str(f))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module] if isinstance(node, ast.ImportFrom) and node.module and not node.level else []
            for n in names:
                if n.split(".")[0] in PROJECT_PACKAGES and n not in found:
                    found.add(n)
                    if (n.startswith("eval.") and not n.startswith("eval.pipeline")
                            and (REPO / (n.replace(".", "/") + ".py")).is_file()):
                        todo.append(n)
    return found


def test_ground_truth_align_code_covers_what_it_imports():
    """The `@gt_poses` align stage's key covers every project module `eval.baselines` runs (`register_sim3` of
    `eval.heldout` places a variant's points): an edit in one re-runs it."""
    from eval.methods import GT_ALIGN_CODE

    code = {"eval.baselines", *GT_ALIGN_CODE}
    uncovered = {m for m in _imported_project_modules("eval.baselines")
                 if not any(m == c or m.startswith(c + ".") for c in code)}
    assert not uncovered
