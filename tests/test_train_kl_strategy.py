"""KLStrategy (GauHuman's density control): the KL divergence of two 3D Gaussians, nearest
neighbours, and its defining operations on hand-made pairs: a candidate with a distinct neighbour
is cloned (small) or split (large), a near-identical small pair is merged into one, and every
per-Gaussian tensor stays aligned."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.strategies import render_with_grad
from torch.distributions import MultivariateNormal
from torch.distributions import kl_divergence as torch_kl

from eva_engine.avatar import CanonicalGaussians
from eva_engine.render import quat_to_rotmat
from eva_engine.train import preset, with_method
from eva_engine.train.strategy import KLStrategy, ops
from eva_engine.train.strategy.kl import disjoint_pairs, kl_divergence, nearest_neighbours

R = 5
HIGH = 1e-3  # mean screen-space gradient above 3DGS's 2e-4 (a 2x2 image: NDC scale 1)


def random_gaussians(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.1
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.05 + 0.005
    return means, quats, scales


def test_kl_divergence_matches_the_closed_form_of_torch_distributions():
    m0, q0, s0 = random_gaussians(16, 0)
    m1, q1, s1 = random_gaussians(16, 1)
    ours = kl_divergence(m0, q0, s0, m1, q1, s1)

    def dist(m, q, s):
        r = quat_to_rotmat(q).double()
        cov = r @ torch.diag_embed(s.double() ** 2) @ r.transpose(1, 2)
        return MultivariateNormal(m.double(), covariance_matrix=cov)

    reference = torch_kl(dist(m0, q0, s0), dist(m1, q1, s1))
    torch.testing.assert_close(ours.double(), reference, rtol=1e-3, atol=1e-4)
    # Zero for identical Gaussians (any quaternion norm), positive and asymmetric otherwise.
    same = kl_divergence(m0, 3.0 * q0, s0, m0, q0, s0)
    torch.testing.assert_close(same, torch.zeros(16), atol=1e-4, rtol=0)
    assert torch.all(ours > 0)
    assert not torch.allclose(ours, kl_divergence(m1, q1, s1, m0, q0, s0))


def test_kl_divergence_is_finite_for_tiny_and_huge_scales():
    m, q, s = random_gaussians(4, 2)
    for scale in (1e-6, 1e3):
        kl = kl_divergence(m, q, s * scale, m + 1e-3, q, s * scale)
        assert torch.all(torch.isfinite(kl))


def test_nearest_neighbours_never_returns_the_point_itself():
    points = torch.tensor([[0.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0], [1.2, 0, 0], [5.0, 0, 0]])
    assert nearest_neighbours(points).tolist() == [1, 0, 3, 2, 3]


def test_disjoint_pairs_take_each_gaussian_once_lowest_kl_first():
    selected = torch.tensor([True, True, True, False])
    partner = torch.tensor([1, 0, 1, 2])  # 0 and 1 are mutual neighbours; 2's is 1
    key = torch.tensor([0.05, 0.05, 0.01, 0.0])
    assert disjoint_pairs(selected, partner, key).tolist() == [[2, 1]]
    assert disjoint_pairs(torch.zeros(4, dtype=torch.bool), partner, key).shape == (0, 2)


def pairs_scene(offset: float, log_scale: float) -> CanonicalGaussians:
    """Two pairs of Gaussians on their template vertices: pair A (rows 0, 1) ``offset`` apart along
    x, pair B (rows 2, 3) 1 m away and far apart from each other (distinct)."""
    means = torch.tensor([[0.0, 0, 0], [offset, 0, 0], [1.0, 0, 0], [1.0, 0.2, 0]])
    n = len(means)
    splats = {
        "means": means,
        "scales": torch.full((n, 3), log_scale),
        "quats": torch.tensor([1.0, 0, 0, 0]).expand(n, 4).clone(),
        "opacities": torch.tensor([0.0, 2.0, 0.0, 0.0]),
        "sh0": torch.arange(n * 3, dtype=torch.float32).view(n, 1, 3),
        "shN": torch.zeros(n, 3, 3),
    }
    parts = torch.tensor([0, 0, 1, 1])
    return CanonicalGaussians(splats, parts, torch.arange(n), means.clone(), parts)


def adam(gs: CanonicalGaussians) -> dict:
    opts = {k: torch.optim.Adam([p], lr=1e-3) for k, p in gs.splats.items()}
    sum(p.sum() for p in gs.splats.values()).backward()
    for o in opts.values():
        o.step()
        o.zero_grad()
    return opts


def refine_once(gs: CanonicalGaussians, grad: list[float]) -> tuple[dict, dict, dict, dict]:
    """One refinement window with constant screen-space gradients ``grad [N]``; returns the stats,
    optimizers, state and the splats as they were just before the refinement."""
    strategy = KLStrategy(
        refine_start_iter=R,
        refine_stop_iter=100,
        refine_every=R,
        prune_template_dist=0.5,
        reset_opacity_at_start=False,
    )
    opts = adam(gs)
    strategy.check_sanity(gs, opts)
    before = {k: p.detach().clone() for k, p in gs.splats.items()}
    state = strategy.initialize_state()
    stats = {}
    for step in range(R + 1):
        stats = strategy.step_post_backward(gs, opts, state, step, render_with_grad(torch.tensor(grad)))
    return stats, opts, state, before


def assert_aligned(gs: CanonicalGaussians, opts: dict, state: dict) -> None:
    n = len(gs)
    assert gs.part_ids.shape == gs.vertex_ids.shape == (n,)
    assert state["grad2d"].shape == state["count"].shape == (n,)
    for k, p in gs.splats.items():
        assert p.shape[0] == n and opts[k].param_groups[0]["params"][0] is p
        assert opts[k].state[p]["exp_avg"].shape[0] == n


def test_a_small_candidate_is_cloned_only_when_its_neighbour_is_distinct():
    # Pair A 2 cm apart with 3 mm Gaussians: KL ~ 22 > 0.4, both cloned; pair B is not a candidate.
    gs = pairs_scene(offset=0.02, log_scale=math.log(0.003))
    stats, opts, state, before = refine_once(gs, [HIGH, HIGH, 0.0, 0.0])
    assert stats == {"cloned": 2, "split": 0, "merged": 0, "pruned": 0, "gaussians": 6}
    assert_aligned(gs, opts, state)
    # The clones are GauHuman's: drawn from their parent's Gaussian, with its scale and part.
    dist = (gs.means.detach()[4:] - before["means"][:2]).norm(dim=-1)
    assert torch.all(dist > 0) and torch.all(dist < 5 * 0.003 * math.sqrt(3))
    assert torch.equal(gs.splats["scales"].detach()[4:], before["scales"][:2])
    assert torch.equal(gs.means.detach()[:4], before["means"])
    assert gs.part_ids.tolist() == [0, 0, 1, 1, 0, 0]
    assert torch.all(opts["means"].state[gs.splats["means"]]["exp_avg"][4:] == 0)


def test_a_near_identical_small_pair_is_merged_not_cloned():
    # Pair A 0.3 mm apart with 3 mm Gaussians: KL = 0.5 (0.1)^2 = 0.005 < 0.1.
    gs = pairs_scene(offset=3e-4, log_scale=math.log(0.003))
    stats, opts, state, before = refine_once(gs, [HIGH, HIGH, 0.0, 0.0])
    assert stats == {"cloned": 0, "split": 0, "merged": 1, "pruned": 0, "gaussians": 3}
    assert_aligned(gs, opts, state)
    merged = 2  # the survivors first, then the merged Gaussian
    for name in ("means", "sh0", "opacities"):  # the pair's mean
        torch.testing.assert_close(gs.splats[name].detach()[merged], before[name][:2].mean(dim=0))
    torch.testing.assert_close(gs.scales().detach()[merged], before["scales"][0].exp() / 0.8)
    assert torch.equal(gs.means.detach()[:2], before["means"][2:])
    assert gs.part_ids.tolist() == [1, 1, 0]


def test_a_large_candidate_is_split_only_when_its_neighbour_is_distinct():
    # 3 cm Gaussians (above grow_scale3d): pair A 0.3 mm apart is redundant (KL ~ 5e-5, and large
    # Gaussians are never merged), pair B 20 cm apart is split.
    gs = pairs_scene(offset=3e-4, log_scale=math.log(0.03))
    stats, opts, state, before = refine_once(gs, [HIGH, HIGH, HIGH, HIGH])
    assert stats == {"cloned": 0, "split": 2, "merged": 0, "pruned": 0, "gaussians": 6}
    assert_aligned(gs, opts, state)
    assert torch.equal(gs.means.detach()[:2], before["means"][:2])
    children = before["scales"][[2, 3, 2, 3]].exp() / 1.6
    torch.testing.assert_close(gs.scales().detach()[2:], children)
    assert gs.part_ids.tolist() == [0, 0, 1, 1, 1, 1]


def test_the_opacity_reset_at_the_first_refinement():
    gs = pairs_scene(offset=0.02, log_scale=math.log(0.003))
    strategy = KLStrategy(refine_start_iter=R, refine_stop_iter=100, refine_every=R)
    opts, state = adam(gs), strategy.initialize_state()
    for step in range(R + 1):
        strategy.step_post_backward(gs, opts, state, step, render_with_grad(torch.zeros(len(gs))))
    assert gs.opacities().max() <= 2 * strategy.prune_opa + 1e-6


def test_merge_refuses_overlapping_pairs():
    gs = pairs_scene(offset=3e-4, log_scale=-5.0)
    with pytest.raises(ValueError, match="share"):
        ops.merge(gs, adam(gs), {}, torch.tensor([[0, 1], [1, 2]]))


def test_the_gauhuman_method_keeps_the_schedule_and_sets_its_objective():
    base = preset("tiny")
    cfg = with_method(base, "gauhuman+body")
    assert type(cfg.strategy) is KLStrategy
    for field in ("refine_start_iter", "refine_stop_iter", "refine_every", "grow_grad2d", "seed"):
        assert getattr(cfg.strategy, field) == getattr(base.strategy, field)
    assert cfg.loss.photometric == "l1" and cfg.loss.lambda_photometric == 1.0
    assert (cfg.loss.lambda_mask, cfg.loss.lambda_ssim, cfg.loss.lambda_lpips) == (0.1, 0.01, 0.01)
    assert cfg.to_dict()["strategy"]["name"] == "KLStrategy"
