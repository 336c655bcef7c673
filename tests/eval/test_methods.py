"""The evaluation's method registry (`eval.methods.METHODS`): names, folders, labels, pipeline settings."""

from __future__ import annotations

import dataclasses
import pickle

import pytest

from eval.evaluate import EvalConfig
from eval.methods import METHODS, EvalMethod, gt_pose_variant
from eval.pipeline import preset
from eval.pipeline.stages import DENOISE_OUTPUTS
from eval.pipeline.validate import DatasetFolder
from mvgeo.common.errors import InputError

#: The names the results and the documentation use (results.json / results.md rows).
NAMES = ("3dgs_gt_poses", "instantsplat", "nlm_instantsplat", "n2v_round1", "denoise_gs", "ablate_no_selection",
         "ablate_charbonnier", "rounds_1", "rounds_2", "rounds_3", "rounds_4", "n2v_fused_round1",
         "denoise_gs_fused", "product", "oracle_clean")
#: ... then the ground-truth-pose variant of each method with estimated poses.
VARIANTS = tuple(f"{n}@gt_poses" for n in NAMES if n != "3dgs_gt_poses")


def _dataset(tmp_path) -> DatasetFolder:
    return DatasetFolder(root=tmp_path, train=["a", "b"], test=["c"], images={}, clean={"a": tmp_path / "a.png"})


def test_every_name_resolves_in_run_order():
    # the run order: each ablation after the Denoise-GS round 1 it links, each variant after its method
    assert tuple(METHODS) == NAMES + VARIANTS
    assert all(isinstance(m, EvalMethod) and m.name == name for name, m in METHODS.items())
    assert EvalConfig(methods=NAMES + VARIANTS).selected() == list(METHODS.values())
    assert [m.name for m in EvalConfig(methods=("denoise_gs", "ablate_charbonnier", "instantsplat")).selected()] \
        == ["instantsplat", "denoise_gs", "ablate_charbonnier"]
    with pytest.raises(InputError, match="magic"):
        EvalConfig(methods=("magic",))
    with pytest.raises(InputError, match="seeds"):
        EvalConfig(seeds=0)


def test_families_share_folders_and_rounds_n_configs():
    base = preset("fast", views=4)
    own = [m for m in METHODS.values() if m.gt_pose_variant_of is None]
    assert {m.name for m in own if m.family == "n2v"} == {
        "n2v_round1", "denoise_gs", "rounds_1", "rounds_2", "rounds_3", "rounds_4"}
    assert {m.name for m in own if m.family == "n2v_fused"} == {"n2v_fused_round1", "denoise_gs_fused"}
    for n in (1, 2, 3, 4):
        cfg = METHODS[f"rounds_{n}"].pipeline_config(base)
        assert cfg.rounds == n and cfg == dataclasses.replace(METHODS["denoise_gs"].pipeline_config(base), rounds=n)
    assert METHODS["n2v_round1"].pipeline_config(base) == METHODS["rounds_1"].pipeline_config(base)
    assert METHODS["denoise_gs"].pipeline_config(base).rounds == 2
    ablation = METHODS["ablate_no_selection"].pipeline_config(base)
    assert ablation.select_views is False and ablation.rounds == 2
    charb = METHODS["ablate_charbonnier"].pipeline_config(base)
    assert charb.denoise.round2_loss == "charbonnier" and charb.rounds == 2
    # The ablations differ from denoise_gs only from round 2 on, and start from its round 1.
    for name in ("ablate_no_selection", "ablate_charbonnier"):
        assert METHODS[name].shares_round1_with == METHODS["denoise_gs"].family
    assert METHODS["instantsplat"].pipeline_config(base).rounds == 1


@pytest.mark.parametrize("name", ["fast", "default", "best"])
def test_product_runs_each_preset_as_shipped(name):
    for rounds in (None, 1) if preset(name).denoise.method != "n2v" else (None, 1, 3):
        base = preset(name, views=4, rounds=rounds)
        assert METHODS["product"].pipeline_config(base) == base
        assert METHODS["product"].pipeline_config(base, "neighbor2neighbor") == base  # --denoiser is not its
    assert METHODS["product"].folder("r2r") == "product" and METHODS["product"].row_label("r2r") == "product"


def test_the_paper_loop_aligns_the_denoised_photos_and_the_default_the_better_of_both():
    base = preset("default", views=4)
    assert base.align.photos == "better_of"
    for name in ("instantsplat", "oracle_clean", "n2v_round1", "denoise_gs", "ablate_no_selection"):
        assert METHODS[name].pipeline_config(base).align.photos == "denoised", name  # (b), oracle: their photos
    assert METHODS["product"].pipeline_config(base).align.photos == "better_of"
    oracle, b = METHODS["oracle_clean"].pipeline_config(base), METHODS["instantsplat"].pipeline_config(base)
    assert oracle == dataclasses.replace(b, splat=oracle.splat)  # (b)'s settings but the splat's length ...
    assert METHODS["oracle_clean"].family == "oracle_clean"  # ... in its own folder
    gt = METHODS["3dgs_gt_poses"]
    assert gt.ground_truth_poses and gt.pipeline_config(base).splat.preset == "gt_poses"
    assert gt.pipeline_config(base).splat.iters is None  # InstantSplat's, as (b)'s
    assert [m.name for m in METHODS.values() if m.ground_truth_poses] == ["3dgs_gt_poses", *VARIANTS]


@pytest.mark.parametrize("name", ["fast", "default", "best"])
def test_the_baselines_splat_for_instantsplats_length_the_product_and_the_oracle_for_the_presets(name):
    base = preset(name, views=4)
    for m in ("instantsplat", "nlm_instantsplat", "3dgs_gt_poses", "n2v_round1", "denoise_gs",
              "instantsplat@gt_poses", "denoise_gs@gt_poses"):
        assert METHODS[m].pipeline_config(base).splat.iters is None, m  # splat.train's "instantsplat": 1000
    for m in ("product", "oracle_clean", "product@gt_poses", "oracle_clean@gt_poses", "n2v_fused_round1"):
        assert METHODS[m].pipeline_config(base).splat.iters == base.splat.iters, m
    # --splat-iters: every splat a method runs, its ground-truth-pose variant's method and points included
    for m in EvalConfig(methods=("instantsplat", "product@gt_poses"), splat_iters=300).selected():
        for each in (m, m.gt_pose_variant_of, m.gt_pose_points_from):
            assert each is None or each.pipeline_config(base).splat.iters == 300, each.name
        assert pickle.loads(pickle.dumps(m)) == m  # still a value (sent to Ray workers)
    assert EvalConfig(methods=("product",)).selected() == [METHODS["product"]]


def test_a_gt_pose_variant_is_its_method_with_the_known_pose_splat():
    base = preset("default", views=4)
    for name in VARIANTS:
        v, own = METHODS[name], METHODS[name.removesuffix("@gt_poses")]
        assert v.gt_pose_variant_of == own and v.ground_truth_poses and v.rounds == own.rounds
        assert v.gt_pose_points_from == METHODS["oracle_clean"]  # the same initial points for every variant
        d = "r2r" if own.rounds == 1 else "n2v"  # (other objectives run round 1 only)
        cfg, own_cfg = v.pipeline_config(base, d), own.pipeline_config(base, d)
        assert cfg.splat.preset == "gt_poses" and cfg.splat.iters == own_cfg.splat.iters
        assert dataclasses.replace(cfg, splat=own_cfg.splat) == own_cfg  # only the splat preset differs
        # after its method (the Ray chains), in a folder of its own, labelled after its method's row
        assert v.runs_after(d) == tuple(dict.fromkeys(own.runs_after(d) + ("oracle_clean",)))
        assert v.folder(d) == own.folder(d) + "@gt_poses"
        assert v.row_label(d) == own.row_label(d) + "@gt_poses"
    with pytest.raises(ValueError, match="ground-truth poses"):
        gt_pose_variant(METHODS["3dgs_gt_poses"], METHODS["oracle_clean"])


@pytest.mark.parametrize("name", ["fast", "default"])
def test_only_the_fused_methods_fuse_whatever_the_preset(name):
    for m in METHODS.values():
        if m.name.startswith("product"):
            continue  # the preset's own settings (test_product_runs_each_preset_as_shipped)
        cfg = m.pipeline_config(preset(name))
        assert cfg.fuse_noisy_splat == ("_fused" in m.name), m.name  # (a @gt_poses variant splats the fused photos)
        assert cfg.align.reuse_geometry == ("auto" if "_fused" in m.name else "never"), m.name
        # the paper's loop runs every round; the extension stops where the preset says (all presets: on)
        assert cfg.stop_when_unrefined == ("_fused" in m.name), m.name


def test_labels_and_folders():
    for m in METHODS.values():
        assert m.row_label() == m.name and m.description
        assert m.folder() == (m.family + "@gt_poses" if m.gt_pose_variant_of else m.family)
    takes = {m.name for m in METHODS.values() if m.takes_denoiser}
    own = {"n2v_round1", "denoise_gs", "rounds_1", "rounds_2", "rounds_3", "rounds_4", "n2v_fused_round1",
           "denoise_gs_fused"}
    assert takes == own | {f"{n}@gt_poses" for n in own}
    assert METHODS["n2v_fused_round1"].folder("r2r") == "n2v_fused_r2r"
    assert METHODS["nlm_instantsplat"].folder("r2r") == "nlm_instantsplat"
    with pytest.raises(InputError, match="round 1 only"):
        EvalConfig(methods=("rounds_2",), denoiser="r2r")
    EvalConfig(methods=tuple(m.name for m in METHODS.values() if m.rounds == 1), denoiser="r2r")


def test_stage_sets_declare_what_they_write(tmp_path):
    """The baselines without a network declare `denoised/` alone; the N2V methods the checkpoint too."""
    ds = _dataset(tmp_path)
    classical = {"instantsplat", "nlm_instantsplat", "oracle_clean"}
    classical |= {f"{n}@gt_poses" for n in classical}
    for m in METHODS.values():
        stages = m.stages(ds)
        assert stages.export is None, m.name  # the scores need no viewer files
        assert stages.denoise_outputs == (("denoised",) if m.name in classical else DENOISE_OUTPUTS), m.name
        assert m.name in classical or stages.denoise.__module__ == "eval.pipeline.stages"
        assert m.rounds == 1 or m.name not in classical


def test_methods_pickle(tmp_path):
    """A method (and so a run's task) can be sent to another process."""
    for m in METHODS.values():
        again = pickle.loads(pickle.dumps(m))
        assert again == m and again.pipeline_config(preset("fast")) == m.pipeline_config(preset("fast"))
