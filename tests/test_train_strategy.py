"""Density control: clone / split / prune keep splats, optimizer state, per-Gaussian buffers and
strategy state aligned; DefaultStrategy densifies above the threshold and prunes what it should."""

from __future__ import annotations

import pytest
import torch

from eva_engine.avatar import CanonicalGaussians
from eva_engine.render import RenderOutput
from eva_engine.train.strategy import ContextAwareStrategy, DefaultStrategy, ops

N = 12


def make_gaussians(n: int = N) -> CanonicalGaussians:
    g = torch.Generator().manual_seed(0)
    template = torch.randn(40, 3, generator=g) * 0.2
    splats = {
        "means": template[:n] + 0.001,
        "scales": torch.full((n, 3), -5.0),
        "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
        "opacities": torch.zeros(n),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, 3, 3, generator=g),
    }
    parts = torch.arange(n) % 3
    return CanonicalGaussians(splats, parts, torch.arange(n), template, torch.arange(40) % 3)


def optimizers_after_a_step(gs: CanonicalGaussians) -> dict:
    opts = {k: torch.optim.Adam([p], lr=1e-3) for k, p in gs.splats.items()}
    loss = sum(
        (p * torch.arange(1, p.shape[0] + 1).view(-1, *[1] * (p.ndim - 1))).sum() for p in gs.splats.values()
    )
    loss.backward()
    for o in opts.values():
        o.step()
        o.zero_grad()
    return opts


def exp_avg(opts, gs, name):
    return opts[name].state[gs.splats[name]]["exp_avg"]


def test_duplicate_keeps_everything_aligned():
    gs = make_gaussians()
    opts = optimizers_after_a_step(gs)
    before = {k: exp_avg(opts, gs, k).clone() for k in gs.splats}
    params = {k: p.detach().clone() for k, p in gs.splats.items()}
    state = {"grad2d": torch.arange(N, dtype=torch.float32), "generator": None}
    mask = torch.zeros(N, dtype=torch.bool)
    mask[[1, 4]] = True
    ops.duplicate(gs, opts, state, mask)
    assert len(gs) == N + 2
    for k, p in gs.splats.items():
        assert p.shape[0] == N + 2 and opts[k].param_groups[0]["params"][0] is p
        assert torch.equal(p[:N], params[k]) and torch.equal(p[N:], params[k][[1, 4]])
        ea = exp_avg(opts, gs, k)
        assert torch.equal(ea[:N], before[k]) and torch.all(ea[N:] == 0)
    assert gs.part_ids.tolist()[N:] == [1, 1] and gs.vertex_ids.tolist()[N:] == [1, 4]
    assert state["grad2d"].shape == (N + 2,) and torch.all(state["grad2d"][N:] == 0)
    # The optimizers still step with the new tensors.
    sum(p.sum() for p in gs.splats.values()).backward()
    for o in opts.values():
        o.step()


def test_split_samples_children_and_removes_parents():
    gs = make_gaussians()
    opts = optimizers_after_a_step(gs)
    before = exp_avg(opts, gs, "means").clone()
    means = gs.means.detach().clone()
    log_scales = gs.splats["scales"].detach().clone()
    state = {"count": torch.ones(N)}
    mask = torch.zeros(N, dtype=torch.bool)
    mask[[0, 5, 7]] = True
    ops.split(gs, opts, state, mask, generator=torch.Generator().manual_seed(0))
    keep = [i for i in range(N) if i not in (0, 5, 7)]
    assert len(gs) == N - 3 + 6
    assert torch.equal(gs.means[: N - 3], means[keep])
    assert torch.equal(exp_avg(opts, gs, "means")[: N - 3], before[keep])
    assert torch.all(exp_avg(opts, gs, "means")[N - 3 :] == 0)
    # Children: near their parent (within a few sigma), scales / 1.6, parent's part and vertex.
    children = gs.means[N - 3 :].view(2, 3, 3)
    assert (children - means[[0, 5, 7]]).norm(dim=-1).max() < 6 * torch.exp(torch.tensor(-5.0)) * 3**0.5
    torch.testing.assert_close(
        gs.splats["scales"][N - 3 :], log_scales[[0, 5, 7]].repeat(2, 1) - torch.log(torch.tensor(1.6))
    )
    assert gs.part_ids[N - 3 :].tolist() == [0, 2, 1] * 2 and gs.vertex_ids[N - 3 :].tolist() == [0, 5, 7] * 2
    assert state["count"].tolist() == [1.0] * (N - 3) + [0.0] * 6


def test_remove_and_reset():
    gs = make_gaussians()
    opts = optimizers_after_a_step(gs)
    before = exp_avg(opts, gs, "sh0").clone()
    mask = torch.zeros(N, dtype=torch.bool)
    mask[[2, 3, 11]] = True
    state = {"grad2d": torch.arange(N, dtype=torch.float32)}
    ops.remove(gs, opts, state, mask)
    keep = [i for i in range(N) if i not in (2, 3, 11)]
    assert len(gs) == N - 3 and gs.vertex_ids.tolist() == keep
    assert torch.equal(exp_avg(opts, gs, "sh0"), before[keep])
    assert state["grad2d"].tolist() == [float(i) for i in keep]
    ops.reset_opacity(gs, opts, state, 0.01)
    assert gs.opacities().max() <= 0.01 + 1e-6
    assert torch.all(exp_avg(opts, gs, "opacities") == 0)


def fake_render(n: int, grad: torch.Tensor, width: int = 100, height: int = 50) -> RenderOutput:
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = grad
    return RenderOutput(
        image=torch.zeros(height, width, 3),
        alpha=torch.zeros(height, width, 1),
        depth=torch.zeros(height, width, 1),
        means2d=means2d,
        radii=torch.ones(n, dtype=torch.int32),
        depths=torch.ones(n),
        num_intersections=0,
    )


def test_default_strategy_densifies_and_prunes():
    gs = make_gaussians()
    with torch.no_grad():
        gs.splats["scales"][6:] = -3.0  # large: split (max scale 0.05 > 0.01)
        gs.splats["opacities"][3] = -10.0  # transparent: pruned
        gs.splats["means"][9] += 1.0  # far from the template: pruned
    opts = optimizers_after_a_step(gs)
    strategy = DefaultStrategy(
        refine_start_iter=2, refine_stop_iter=10, refine_every=2, prune_template_dist=0.3
    )
    strategy.check_sanity(gs, opts)
    state = strategy.initialize_state()
    # Pixel gradients scaled by (W/2, H/2) = (50, 25): 1e-5 px -> 5e-4 NDC, above 2e-4.
    grad = torch.zeros(N, 2)
    grad[[0, 1, 6, 7], 0] = 1e-5
    grad[[2], 1] = 4e-6  # 1e-4 NDC: below
    stats = {}
    for step in (1, 2):
        stats = strategy.step_post_backward(gs, opts, state, step, fake_render(len(gs), grad.clone()))
    parts = stats.pop("parts")
    assert stats == {"cloned": 2, "split": 2, "pruned": 2, "gaussians": N + 2 + 2 - 2}
    # Per part: the same counts, split by part, and the (constant) threshold.
    assert sum(p["cloned"] for p in parts.values()) == 2 and sum(p["split"] for p in parts.values()) == 2
    assert all(p["eps_clone"] in (None, pytest.approx(strategy.grow_grad2d)) for p in parts.values())
    assert len(gs) == N + 2 and gs.part_ids.shape == (N + 2,)
    assert torch.all(state["grad2d"] == 0) and state["grad2d"].shape == (N + 2,)
    for k, p in gs.splats.items():
        assert opts[k].state[p]["exp_avg"].shape[0] == len(gs)
    assert gs.template_distance().max() < 0.3
    # Outside the window nothing happens.
    assert (
        strategy.step_post_backward(gs, opts, state, 10, fake_render(len(gs), torch.ones(len(gs), 2))) == {}
    )


@pytest.mark.parametrize("cls", [DefaultStrategy, ContextAwareStrategy])
def test_a_second_view_counts_toward_densification(cls):
    """``observe_view`` (a face close-up of the step's frame): its NDC gradients join the window
    and each Gaussian it shows counts one more visible step; Gaussians it culls keep the frame's
    mean. After ``refine_stop_iter`` it adds nothing."""
    gs = make_gaussians()
    opts = optimizers_after_a_step(gs)
    strategy = cls(refine_start_iter=100, refine_stop_iter=10)
    state = strategy.initialize_state()
    frame = torch.zeros(N, 2)
    frame[:, 0] = 2e-6  # 1e-4 NDC at W = 100: below 2e-4
    close = torch.zeros(N, 2)
    close[:, 0] = 1e-5  # 5e-4 NDC at W = 100
    view = off_screen(fake_render(N, close), torch.arange(N) >= 6)
    strategy.observe_view(gs, state, 1, view)
    strategy.step_post_backward(gs, opts, state, 1, fake_render(N, frame))
    mean = state["grad2d"] / state["count"].clamp_min(1)
    assert state["count"].tolist() == [2.0] * 6 + [1.0] * 6
    assert torch.allclose(mean, torch.tensor([3e-4] * 6 + [1e-4] * 6))
    assert (mean > strategy.grow_grad2d).tolist() == [True] * 6 + [False] * 6
    if cls is ContextAwareStrategy:  # its window sums see both views too
        assert torch.allclose(state["win_sum"], state["grad2d"])
        assert torch.equal(state["win_count"], state["count"])
    before = state["grad2d"].clone()
    strategy.observe_view(gs, state, 10, fake_render(N, close))
    assert torch.equal(state["grad2d"], before)


def test_pruning_never_empties_the_avatar():
    """When every Gaussian meets a prune rule (all transparent; all never seen at the end), the
    strategy keeps them all rather than leave an avatar with nothing to render."""
    gs = make_gaussians()
    with torch.no_grad():
        gs.splats["opacities"][:] = -10.0
    opts = optimizers_after_a_step(gs)
    strategy = DefaultStrategy(refine_start_iter=2, refine_stop_iter=10, refine_every=2)
    state = strategy.initialize_state()
    assert strategy.prune(gs, opts, state) == 0 and len(gs) == N
    state["seen"] = torch.zeros(N)
    finished = DefaultStrategy(prune_never_seen=True)
    assert finished.finalize(gs, opts, state) == {} and len(gs) == N


def test_check_sanity_rejects_foreign_optimizers():
    gs = make_gaussians()
    opts = {"means": torch.optim.Adam([torch.nn.Parameter(torch.zeros(3))])}
    with pytest.raises(ValueError, match="exactly"):
        DefaultStrategy().check_sanity(gs, opts)


def off_screen(render: RenderOutput, rows: torch.Tensor) -> RenderOutput:
    """``render`` with ``rows`` culled (radius 0, no gradient), as off-screen Gaussians are."""
    render.radii[rows] = 0
    render.means2d.grad[rows] = 0.0
    return render


@pytest.mark.parametrize("prune", [True, False])
def test_parts_never_seen_are_removed_after_training(prune):
    """Hands (part 1) off screen in every step: finalize removes exactly them, keeping splats,
    optimizer state and buffers aligned; with ``prune_unseen_parts=False`` nothing changes."""
    gs = make_gaussians()
    opts = optimizers_after_a_step(gs)
    strategy = DefaultStrategy(refine_start_iter=100, prune_unseen_parts=prune)
    state = strategy.initialize_state()
    hands = gs.part_ids == 1
    for step in range(4):
        grad = torch.full((N, 2), 1e-7)
        strategy.step_post_backward(gs, opts, state, step, off_screen(fake_render(N, grad), hands))
    assert state["part_seen"] == [4, 0, 4]
    stats = strategy.finalize(gs, opts, state)
    if not prune:
        assert stats == {} and len(gs) == N
        return
    assert stats == {"unseen_parts": ["hand"], "pruned": N // 3, "gaussians": N - N // 3}
    assert len(gs) == N - N // 3 and not bool((gs.part_ids == 1).any())
    assert gs.vertex_ids.shape == (len(gs),)
    for k, p in gs.splats.items():
        assert opts[k].state[p]["exp_avg"].shape[0] == len(gs)


def test_a_part_seen_once_is_kept_and_nothing_seen_removes_nothing():
    gs = make_gaussians()
    opts = optimizers_after_a_step(gs)
    strategy = DefaultStrategy(refine_start_iter=100)
    state = strategy.initialize_state()
    hands = gs.part_ids == 1
    grad = torch.full((N, 2), 1e-7)
    strategy.step_post_backward(gs, opts, state, 0, off_screen(fake_render(N, grad.clone()), hands))
    strategy.step_post_backward(gs, opts, state, 1, fake_render(N, grad.clone()))  # hands seen once
    assert strategy.finalize(gs, opts, state) == {} and len(gs) == N
    # On screen but with exactly zero gradient (fully occluded) does not count as seen.
    state = strategy.initialize_state()
    strategy.step_post_backward(gs, opts, state, 0, fake_render(N, torch.zeros(N, 2)))
    assert state["part_seen"] == [0, 0, 0]
    assert strategy.finalize(gs, opts, state) == {} and len(gs) == N  # never remove everything
