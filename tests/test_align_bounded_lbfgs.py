"""L-BFGS-B over torch tensors (``align.bounded_lbfgs``) and the fit stages that use it."""

from __future__ import annotations

import pytest
import torch

from eva_engine.align.bounded_lbfgs import minimize_bounded


def test_bounded_entries_stop_at_their_bounds_and_free_ones_reach_the_optimum():
    a = torch.full((3,), 0.5)
    b = torch.zeros(2, dtype=torch.float64)
    want_a, want_b = torch.tensor([-0.5, 0.3, 2.0]), torch.tensor([5.0, -5.0], dtype=torch.float64)

    def loss():
        return (a - want_a).square().sum() + (b - want_b).square().sum()

    calls = minimize_bounded([a, b], [(0.0, 1.0), None], loss, iterations=50, history_size=10)
    assert calls >= 1
    torch.testing.assert_close(a, torch.tensor([0.0, 0.3, 1.0]), atol=1e-6, rtol=0)
    torch.testing.assert_close(b, want_b, atol=1e-6, rtol=0)
    assert a.dtype == torch.float32 and b.dtype == torch.float64  # dtypes kept
    assert not a.requires_grad and a.grad is None


def test_a_start_outside_the_bounds_is_clipped_before_the_first_evaluation():
    x = torch.tensor([-3.0, 4.0])
    seen = []

    def loss():
        seen.append(x.detach().clone())
        return (x - 0.5).square().sum()

    minimize_bounded([x], [(0.0, 1.0)], loss, iterations=5, history_size=5)
    assert seen[0].tolist() == [0.0, 1.0]
    assert all(((s >= 0) & (s <= 1)).all() for s in seen)


def test_a_flat_loss_ends_without_leaving_the_bounds():
    x = torch.tensor([0.2, 0.9])
    minimize_bounded([x], [(0.0, 1.0)], lambda: (x * 0.0).sum(), iterations=10, history_size=5)
    assert torch.isfinite(x).all() and ((x >= 0) & (x <= 1)).all()


def test_bounds_must_match_the_tensors():
    with pytest.raises(ValueError, match="bounds"):
        minimize_bounded([torch.zeros(2)], [None, None], lambda: torch.zeros(()), 1, 1)


def test_the_face_stage_keeps_the_expression_in_range_and_the_old_optimiser_did_not(anny_model):
    """The face stage has no range penalty. With L-BFGS-B every coefficient stays in [0, 1]
    through the stage (before the fit's final clamp); torch's L-BFGS took some below 0."""
    import dataclasses

    from eva_engine.align.evaluate import targets_from_params
    from eva_engine.align.objective import FitProblem
    from eva_engine.align.stages import FitConfig, default_stages
    from eva_engine.render import intrinsics, orbit_camera

    names = anny_model.expression_names
    truth = anny_model.default_params(2)
    actions = {"jawOpen": 0.3, "mouthSmileLeft": 0.6, "eyeBlinkLeft": 0.8, "browInnerUp": 0.7}
    for name, value in actions.items():
        truth.expression[:, names.index(name)] = value
    K, view = intrinsics(256, 256, 40.0), orbit_camera(0.0, 0.0, 1.2, target=(0.0, 0.5, 0.0))
    targets = targets_from_params(anny_model, truth, K, view, image_size=(256, 256))
    start = truth.map(lambda t: t.clone())
    start.expression.zero_()
    face = dataclasses.replace(next(s for s in default_stages() if s.name == "face"), iterations=40)
    seen = {}
    for bounded in (True, False):
        config = FitConfig(stages=(face,), bounded_expression=bounded)
        problem = FitProblem(anny_model, targets, config, start)
        problem.run_stage(face, None)
        seen[bounded] = problem.values["expression"]
    assert seen[True].min() >= 0 and seen[True].max() <= 1
    assert seen[False].min() < 0
