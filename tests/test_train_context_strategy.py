"""ContextAwareStrategy (EVA §3.3): thresholds from constructed gradient histories (per Gaussian
and per part), part and history inheritance through clone/split, same-part distance pruning,
selection by config."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from helpers.scenes import teacher_scene
from helpers.strategies import render_with_grad

from eva_engine.avatar import CanonicalGaussians
from eva_engine.train import (
    METHODS,
    AvatarLoss,
    ConfidenceLoss,
    LossConfig,
    preset,
    train_avatar,
    with_method,
)
from eva_engine.train.strategy import ContextAwareStrategy, DefaultStrategy, KLStrategy

R = 5
BODY, HAND, FACE = 0, 1, 2


def gaussians(parts: list[int], log_scale: float = -6.0, seed: int = 0) -> CanonicalGaussians:
    """Gaussians on (a copy of) their own template vertices: template vertex i has part parts[i]."""
    g = torch.Generator().manual_seed(seed)
    n = len(parts)
    template = torch.randn(n, 3, generator=g) * 0.3
    splats = {
        "means": template.clone(),
        "scales": torch.full((n, 3), log_scale),
        "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).clone(),
        "opacities": torch.zeros(n),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.zeros(n, 3, 3),
    }
    p = torch.tensor(parts)
    return CanonicalGaussians(splats, p, torch.arange(n), template, p)


def drive(strategy, gs, history: list[torch.Tensor], visible=None) -> dict:
    """Feed one gradient vector per step from step 0; returns the state just before step
    len(history)'s refinement would run (statistics of that step included)."""
    state = strategy.initialize_state()
    for step, grad in enumerate(history[:-1]):
        strategy.step_post_backward(gs, {}, state, step, render_with_grad(grad, visible))
    strategy.update_state(gs, state, render_with_grad(history[-1], visible))
    return state


def two_windows(prev: list[float], cur: list[float]) -> list[torch.Tensor]:
    """Steps 0..2R: constant ``prev`` in the first window (steps 0..R), ``cur`` in the second."""
    return [torch.tensor(prev)] * (R + 1) + [torch.tensor(cur)] * R


def strategy(**kw) -> ContextAwareStrategy:
    return ContextAwareStrategy(refine_start_iter=2 * R, refine_stop_iter=100, refine_every=R, **kw)


def test_per_gaussian_thresholds_follow_the_formula():
    parts = [BODY, BODY, HAND, HAND, FACE, FACE]
    prev = [1.0e-4, 2.0e-4, 1.0e-4, 1.0e-4, 3.0e-4, 1.0e-4]
    cur = [1.1e-4, 1.5e-4, 1.05e-4, 0.9e-4, 3.0e-4, 1.1e-3]
    gs, s = gaussians(parts), strategy()
    eps = s.densify_thresholds(drive(s, gs, two_windows(prev, cur)), gs)
    e, lam = torch.tensor(s.part_grad_base)[parts], torch.tensor(s.part_grad_lambda)[parts]
    expected = e + lam * (torch.tensor(cur) - torch.tensor(prev))
    # Rising gradients lower the threshold, falling ones raise it, flat ones keep e_part.
    assert eps[:5] == pytest.approx(expected[:5], rel=1e-4)
    assert eps[0] < 2e-4 < eps[1] and eps[2] < 1e-4 < eps[3] and eps[4] == pytest.approx(1.4e-4, rel=1e-4)
    # A steep rise is floored (a threshold <= 0 would densify everything).
    assert expected[5] < 0 and eps[5] == pytest.approx(s.min_threshold_ratio * 1.4e-4)


def test_per_gaussian_history_is_normalised_by_visibility():
    gs, s = gaussians([BODY, BODY]), strategy()
    # Gaussian 1 is seen every other step in the second window only, with the same gradient.
    history = two_windows([2e-4, 2e-4], [2e-4, 2e-4])
    vis = [torch.tensor([True, True])] * (R + 1) + [torch.tensor([True, k % 2 == 0]) for k in range(R)]
    state = s.initialize_state()
    for step, (grad, v) in enumerate(zip(history[:-1], vis[:-1], strict=True)):
        s.step_post_backward(gs, {}, state, step, render_with_grad(grad, v))
    s.update_state(gs, state, render_with_grad(history[-1], vis[-1]))
    assert s.densify_thresholds(state, gs) == pytest.approx(torch.full((2,), 2e-4), rel=1e-4)


def test_part_mean_thresholds_use_the_part_means():
    parts = [BODY, BODY, HAND, HAND, FACE]
    prev = [1.0e-4, 3.0e-4, 1.0e-4, 1.0e-4, 2.0e-4]
    cur = [2.0e-4, 2.2e-4, 1.0e-4, 1.2e-4, 1.9e-4]
    gs, s = gaussians(parts), strategy(history="part_mean")
    eps = s.densify_thresholds(drive(s, gs, two_windows(prev, cur)), gs)
    body = 2e-4 - 9.0 * ((2.0e-4 + 2.2e-4) / 2 - (1.0e-4 + 3.0e-4) / 2)
    hand = 1e-4 - 4.5 * ((1.0e-4 + 1.2e-4) / 2 - 1.0e-4)
    face = 1.4e-4 - 6.3 * (1.9e-4 - 2.0e-4)
    assert eps == pytest.approx(torch.tensor([body, body, hand, hand, face]), rel=1e-4)
    # The official form's weights: e and λ are (1, 0.5, 0.7) times (2e-4, -9).
    w = torch.tensor([1.0, 0.5, 0.7])
    assert torch.tensor(s.part_grad_base) == pytest.approx(2e-4 * w)
    assert torch.tensor(s.part_grad_lambda) == pytest.approx(-9.0 * w)


def test_no_previous_window_means_no_history_term():
    gs, s = gaussians([BODY, HAND, FACE]), strategy()
    state = s.initialize_state()
    s.update_state(gs, state, render_with_grad(torch.tensor([1e-3, 1e-3, 1e-3])))
    assert s.densify_thresholds(state, gs) == pytest.approx(torch.tensor(s.part_grad_base))


def test_a_gaussian_budget_keeps_the_candidates_furthest_above_their_own_threshold():
    """max_gaussians = N + 1: one densification. A hand Gaussian 1.5x over its 1e-4 beats a body
    Gaussian 1.25x over its 2e-4 although its gradient is smaller."""
    gs = gaussians([BODY, HAND, FACE])
    s = strategy(max_gaussians=4, part_prune_dist=None, prune_template_dist=10.0)
    state = drive(s, gs, [torch.tensor([2.5e-4, 1.5e-4, 0.5e-4])] * (2 * R + 1))
    stats = s.refine(gs, {}, state)
    assert stats["cloned"] == 1 and len(gs) == 4 and gs.part_ids.tolist() == [BODY, HAND, FACE, HAND]
    # The baseline (one threshold for all) takes the largest gradient.
    gs = gaussians([BODY, HAND, FACE])
    base = DefaultStrategy(
        refine_start_iter=2 * R, refine_every=R, max_gaussians=4, grow_grad2d=1e-4, prune_template_dist=10.0
    )
    state = drive(base, gs, [torch.tensor([2.5e-4, 1.5e-4, 0.5e-4])] * (2 * R + 1))
    base.refine(gs, {}, state)
    assert gs.part_ids.tolist() == [BODY, HAND, FACE, BODY]


def test_refine_keeps_state_aligned_and_children_inherit_part_and_history():
    parts = [BODY, HAND, FACE, BODY, HAND, FACE, BODY, FACE]
    gs = gaussians(parts, seed=1)
    with torch.no_grad():
        gs.splats["scales"][2] = -3.9  # ~0.02 m: split (face); the others are small: clone
    s = strategy(part_prune_dist=(1.0, 1.0, 1.0))
    # Gaussians 1 (hand) and 2 (face) exceed their thresholds; each has its own history.
    prev = [1e-5, 2e-5, 3e-5, 4e-5, 5e-5, 6e-5, 7e-5, 8e-5]
    cur = [1e-5, 4e-4, 5e-4, 4e-5, 5e-5, 6e-5, 7e-5, 8e-5]
    state = drive(s, gs, two_windows(prev, cur))
    opts = {k: torch.optim.Adam([p], lr=1e-3) for k, p in gs.splats.items()}
    stats = s.refine(gs, opts, state)
    assert stats["cloned"] == 1 and stats["split"] == 1 and stats["pruned"] == 0
    n = len(gs)
    assert n == 8 + 1 + 1
    for key in ("grad2d", "count", "win_sum", "win_count", "prev_mean", "prev_seen"):
        assert state[key].shape == (n,), key
    assert "origin" not in state
    assert torch.all(state["win_sum"] == 0) and torch.all(state["win_count"] == 0)
    # Survivors: 0, 1, 3..7 (2 was split); then the clone of 1; then the two children of 2.
    assert gs.part_ids.tolist() == [BODY, HAND, BODY, HAND, FACE, BODY, FACE, HAND, FACE, FACE]
    expected_prev = torch.tensor([cur[i] for i in (0, 1, 3, 4, 5, 6, 7, 1, 2, 2)])
    assert state["prev_mean"] == pytest.approx(expected_prev, rel=1e-5)
    assert torch.all(state["prev_seen"] == 1)


def test_refine_rolls_windows_before_densification_starts():
    gs, s = gaussians([BODY, HAND]), strategy()
    s = ContextAwareStrategy(refine_start_iter=4 * R, refine_stop_iter=100, refine_every=R)
    history = [torch.tensor([1e-4, 1e-4])] * (R + 1) + [torch.tensor([2e-4, 3e-4])] * R
    history += [torch.tensor([2.5e-4, 3e-4])] * R
    state = drive(s, gs, history)
    assert state["prev_mean"] == pytest.approx(torch.tensor([2e-4, 3e-4]))
    cur, _ = s.window_mean(state)
    assert cur == pytest.approx(torch.tensor([2.5e-4, 3e-4]))


def test_same_part_distance_pruning():
    # Template: a body vertex at the origin, a hand vertex 0.2 m away, a face vertex 0.4 m away.
    template = torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.4, 0.0, 0.0]])
    tparts = torch.tensor([BODY, HAND, FACE])
    # hand Gaussian on the body vertex (0.2 m from any hand vertex), body 0.04 m off its vertex,
    # face 0.07 m off its vertex, hand 0.04 m off its vertex.
    means = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.04, 0.0], [0.4, 0.07, 0.0], [0.2, 0.04, 0.0]])
    parts = torch.tensor([HAND, BODY, FACE, HAND])
    n = 4
    splats = {
        "means": means,
        "scales": torch.full((n, 3), -6.0),
        "quats": torch.eye(4)[:1].expand(n, 4),
        "opacities": torch.zeros(n),
        "sh0": torch.zeros(n, 1, 3),
        "shN": torch.zeros(n, 3, 3),
    }
    make = lambda: CanonicalGaussians(splats, parts, torch.zeros(n, dtype=torch.long), template, tparts)  # noqa: E731

    def refined(strategy) -> list[int]:
        gs = make()
        state = strategy.initialize_state()
        strategy.update_state(gs, state, render_with_grad(torch.zeros(n)))
        strategy.refine(gs, {k: torch.optim.Adam([p]) for k, p in gs.splats.items()}, state)
        return gs.part_ids.tolist()

    # Context-aware: the stray hand Gaussian (0) and the body one 0.04 m out (1) go; the face
    # (limit 0.09) and the hand (limit 0.05) stay.
    assert refined(strategy()) == [FACE, HAND]
    # The baseline measures to any vertex with 0.05 m: the stray hand Gaussian and the body one
    # stay, the face one 0.07 m out goes.
    assert refined(DefaultStrategy(refine_start_iter=0, refine_stop_iter=100)) == [HAND, BODY, HAND]
    # The option off: the baseline's rule.
    assert refined(strategy(part_prune_dist=None)) == [HAND, BODY, HAND]


def test_invalid_configuration_is_refused():
    with pytest.raises(ValueError, match="history"):
        ContextAwareStrategy(history="ema")
    with pytest.raises(ValueError, match="one value per part"):
        ContextAwareStrategy(part_grad_base=(1e-4, 2e-4))


def test_selection_by_config_keeps_the_schedule():
    base = preset("tiny")
    eva = with_method(base, "eva")
    assert type(eva.strategy) is ContextAwareStrategy and eva.strategy.history == "per_gaussian"
    for field in ("refine_start_iter", "refine_stop_iter", "refine_every", "grow_grad2d", "seed"):
        assert getattr(eva.strategy, field) == getattr(base.strategy, field)
    assert eva.loss.photometric == "confidence" and eva.loss.lambda_lpips == base.loss.lambda_lpips
    assert isinstance(AvatarLoss(eva.loss, lpips=object()).photometric, ConfidenceLoss)
    # EVA's weights but 3DGS's SSIM weight (the paper's 0.01 measured worse: train/losses.py)
    assert (eva.loss.lambda_photometric, eva.loss.lambda_ssim, eva.loss.lambda_lpips) == (1.0, 0.2, 0.04)
    baseline = with_method(eva, "3dgs+body")  # switching back needs no fresh preset
    assert type(baseline.strategy) is DefaultStrategy and baseline.loss.photometric == "l1"
    # 3DGS's own objective: 0.8 L1 + 0.2 D-SSIM (plus the mask term), no LPIPS
    assert baseline.loss.lambda_photometric == 0.8 and baseline.loss.lambda_ssim == 0.2
    assert baseline.loss.lambda_lpips == 0 and baseline.loss.lambda_mask == eva.loss.lambda_mask
    assert baseline.loss.pixel_norm == eva.loss.pixel_norm == "person_box"
    assert baseline.avatar == eva.avatar and baseline.optim == eva.optim
    assert baseline.iterations == eva.iterations
    assert type(with_method(base, "eva-no-cadc").strategy) is DefaultStrategy
    assert with_method(base, "eva-no-cl").loss.photometric == "l1"
    assert with_method(base, "eva-part-mean").strategy.history == "part_mean"
    assert eva.to_dict()["strategy"]["name"] == "ContextAwareStrategy"
    with pytest.raises(ValueError, match="unknown method"):
        with_method(base, "gart")


@pytest.fixture(scope="module")
def tiny_scene(anny_model):
    return teacher_scene(anny_model, n_frames=4, size=40)[0]


@pytest.mark.parametrize("method", METHODS)
def test_tiny_end_to_end_run_with_each_method(method, tiny_scene, anny_model):
    """A couple of dozen steps with each ablation switch: refinements happen, every per-Gaussian
    tensor stays aligned, the loss stays finite. (LPIPS off: its network is the slow part here.)"""
    base = preset("tiny", iterations=22, loss=LossConfig(lambda_lpips=0.0))
    schedule = dict(refine_start_iter=10, refine_stop_iter=22, refine_every=5)
    base = dataclasses.replace(base, strategy=dataclasses.replace(base.strategy, **schedule))
    config = with_method(base, method)
    result = train_avatar(tiny_scene, config, body=anny_model)
    gs = result.avatar.gaussians
    # The official recipe densifies one interval later (its ``iteration > densify_from_iter``).
    steps = [15, 20] if METHODS[method].recipe == "official" else [10, 15, 20]
    assert [r["step"] for r in result.refinements] == steps
    assert all(math.isfinite(v) for v in result.losses)
    assert gs.part_ids.shape == gs.vertex_ids.shape == (len(gs),)
    assert set(gs.part_ids.unique().tolist()) <= {BODY, HAND, FACE}
    kinds = {"3dgs": DefaultStrategy, "gart": DefaultStrategy, "cadc": ContextAwareStrategy, "kl": KLStrategy}
    assert type(config.strategy) is kinds[METHODS[method].density]


# -- the official code's densification (history="official") ---------------------------------
SPLIT, CLONE = -3.9, -6.0  # log-scales: ~0.02 m (split-sized) and ~0.0025 m (clone-sized)


def official_gaussians(parts: list[int], log_scales: list[float]) -> CanonicalGaussians:
    gs = gaussians(parts)
    with torch.no_grad():
        gs.splats["scales"].copy_(torch.tensor(log_scales)[:, None].expand(-1, 3))
    return gs


def official() -> ContextAwareStrategy:
    return strategy(history="official", part_prune_dist=(10.0, 10.0, 10.0))


def test_official_first_event_bursts_with_no_history_and_clones_keep_e():
    """First event: prev = 0, Δ = the mean gradient over every Gaussian (all parts), λ on
    split-sized Gaussians only, and no floor: every split-sized Gaussian splits, even one that
    was never seen; a clone-sized one just under its e_part does not clone."""
    parts = [BODY, BODY, BODY, HAND, HAND, FACE]
    scales = [SPLIT, SPLIT, CLONE, SPLIT, CLONE, CLONE]
    grads = torch.tensor([0.0, 1e-4, 1.9e-4, 0.5e-4, 0.9e-4, 1.5e-4])
    visible = torch.tensor([False, True, True, True, True, True])  # Gaussian 0 never seen
    gs, s = official_gaussians(parts, scales), official()
    state = drive(s, gs, [grads] * (2 * R + 1), visible)
    eps = s.densify_thresholds(state, gs)
    e = torch.tensor(s.part_grad_base)[parts]
    lam = torch.tensor(s.part_grad_lambda)[parts]
    mean_all = float(grads.sum()) / 6  # unseen counted as 0
    split_sized = torch.tensor([True, True, False, True, False, False])
    expected = torch.where(split_sized, e + lam * mean_all, e)
    assert eps == pytest.approx(expected, rel=1e-5)
    assert bool((eps[split_sized] < 0).all())  # no floor
    stats = s.refine(gs, {k: torch.optim.Adam([p], lr=1e-3) for k, p in gs.splats.items()}, state)
    assert stats["split"] == 3 and stats["cloned"] == 1  # the face Gaussian: 1.5e-4 > 1.4e-4
    assert stats["parts"]["body"]["split"] == 2 and stats["parts"]["body"]["cloned"] == 0
    assert stats["parts"]["hand"] == pytest.approx(
        {
            "n": 2,
            "g_mean": 0.7e-4,
            "eps_clone": 1e-4,
            "eps_split": 1e-4 - 4.5 * mean_all,
            "cloned": 0,
            "split": 1,
        }
    )
    # This event's part means (of the Gaussians before densifying) become the history.
    assert state["part_prev"] == pytest.approx([(0 + 1e-4 + 1.9e-4) / 3, 0.7e-4, 1.5e-4])


def test_official_later_events_use_part_means_with_clones_as_zeros_and_lambda_on_splits_only():
    parts = [BODY, BODY, BODY, HAND, HAND]
    scales = [CLONE, SPLIT, SPLIT, CLONE, SPLIT]
    grads = torch.tensor([3e-4, 1e-4, 2e-4, 0.2e-4, 0.6e-4])
    gs, s = official_gaussians(parts, scales), official()
    state = drive(s, gs, [grads] * (2 * R + 1))
    state["part_prev"] = [1e-4, 0.5e-4, 0.0]  # as a previous event left it
    eps = s.densify_thresholds(state, gs)
    # Body: Gaussian 0 clones (3e-4 > 2e-4) and counts as a zero in the split's part mean.
    body = 2e-4 - 9.0 * ((3e-4 + 1e-4 + 2e-4) / 4 - 1e-4)
    hand = 1e-4 - 4.5 * ((0.2e-4 + 0.6e-4) / 2 - 0.5e-4)  # no hand clone
    assert eps == pytest.approx(torch.tensor([2e-4, body, body, 1e-4, hand]), rel=1e-5)
    # The per-Gaussian form on the same history: λ would move the clone's threshold too, and
    # no part mean would count a zero for it.
    other = strategy(history="part_mean")
    other_state = drive(other, gs, [grads] * (2 * R + 1))
    assert other.densify_thresholds(other_state, gs)[2] != pytest.approx(body, rel=1e-3)


def test_official_recipe_switches_everything_the_authors_code_sets():
    base = preset("fast")
    cfg = with_method(base, "eva-official")
    s = cfg.strategy
    assert type(s) is ContextAwareStrategy and s.history == "official"
    assert s.refine_start_iter == base.strategy.refine_start_iter + base.strategy.refine_every
    assert cfg.loss.photometric == "confidence_official" and cfg.loss.lpips_net == "vgg"
    assert (
        cfg.loss.lambda_photometric,
        cfg.loss.lambda_mask,
        cfg.loss.lambda_ssim,
        cfg.loss.lambda_lpips,
    ) == (
        1.0,
        0.1,
        0.01,
        0.04,
    )
    assert cfg.avatar.init_opacity == 0.004 and cfg.avatar.init_max_gaussians is None
    assert cfg.background == (0.0, 0.0, 0.0) and cfg.sh_degree_interval == 1000
    o = cfg.optim
    assert (o.means_lr, o.means_lr_steps, o.weight_offsets_lr, o.pose_refine_lr) == (
        1.6e-4,
        30_000,
        5e-5,
        5e-6,
    )
    assert o.pose_refine_part_scale == (1.0, 0.05, 0.05)
    no_cadc = with_method(base, "eva-official-no-cadc")
    assert type(no_cadc.strategy) is DefaultStrategy and no_cadc.loss == cfg.loss
    assert no_cadc.strategy.refine_start_iter == s.refine_start_iter
    # The project's eva is untouched by it.
    assert with_method(base, "eva").loss.lpips_net == "alex"
