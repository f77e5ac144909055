"""Training end to end on a small teacher scene: the loss falls, held-out novel poses beat a
trivial predictor clearly, runs are deterministic, bad data gives a clear error; the losses."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from helpers.scenes import teacher_scene

from eva_engine.avatar import Avatar
from eva_engine.eval import ImageMetrics, evaluate_avatar, metrics_table
from eva_engine.metrics import LPIPS, psnr
from eva_engine.render import RenderOutput
from eva_engine.train import (
    PRESETS,
    AvatarLoss,
    LossConfig,
    TrainingError,
    composite_target,
    preset,
    train_avatar,
    with_method,
    with_overrides,
)
from eva_engine.train.config import OptimConfig
from eva_engine.train.frame_order import ExpressionEventsConfig
from eva_engine.train.trainer import TrainingRun, make_extra_optimizers, means_lr


@pytest.fixture(scope="module")
def scene(anny_model):
    return teacher_scene(anny_model, n_frames=8, size=56)


@pytest.fixture(scope="module")
def lpips():
    return LPIPS()


@pytest.fixture(scope="module")
def trained(scene, anny_model):
    ds, _ = scene
    reports = []
    result = train_avatar(ds, preset("tiny"), body=anny_model, progress=reports.append)
    return result, reports


def trivial_psnr(ds, i: int) -> float:
    """Mean training colour painted inside the (true) test mask, background elsewhere."""
    person = torch.cat([ds[j].image[ds[j].mask > 0.5] for j in ds.splits["train"]])
    f = ds[i]
    pred = composite_target(person.mean(0).expand_as(f.image), f.mask, torch.ones(3))
    target = composite_target(f.image, f.mask, torch.ones(3))
    return float(psnr(pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None])[0])


def test_training_fits_and_generalises_to_novel_poses(trained, scene, lpips):
    result, reports = trained
    ds, _ = scene
    losses = torch.tensor(result.losses)
    assert len(losses) == preset("tiny").iterations
    assert losses[-20:].mean() < 0.75 * losses[:20].mean()
    metrics = ImageMetrics(lpips_alex=lpips)
    ev = evaluate_avatar(result.avatar, ds, metrics=metrics, train_seconds=result.train_seconds)
    baseline = sum(trivial_psnr(ds, i) for i in ds.splits["test_pose"]) / len(ds.splits["test_pose"])
    assert ev.regions["full"].psnr > baseline + 3.0, (ev.regions["full"].psnr, baseline)
    assert set(ev.regions) == {"full", "hand", "face"}
    # Density control ran in its window and the bookkeeping held.
    assert [r["step"] for r in result.refinements] == [40, 60]
    assert len(result.avatar.gaussians) == result.refinements[-1]["gaussians"]
    # Every part is in view here: none is dropped after training.
    assert sum(result.gaussians_per_part["before"].values()) == preset("tiny").avatar.init_max_gaussians
    assert all(n > 0 for n in result.gaussians_per_part["after"].values())
    # Progress: setup, train reports with a falling ETA, done.
    assert reports[0].stage == "setup" and reports[-1].stage == "done"
    train = [r for r in reports if r.stage == "train"]
    assert train[-1].done == preset("tiny").iterations and train[-1].eta == 0.0
    assert all(r.num_gaussians > 0 for r in train)
    assert set(result.timings) >= {"skinning", "rasterize", "losses", "backward", "densify"}
    print(metrics_table({"tiny": ev}), f"trivial PSNR {baseline:.2f}")


@pytest.fixture
def one_thread():
    """Bit-identical runs need one CPU thread: with more, oneDNN's convolution backward (the LPIPS
    term's) sums in a varying order at some image sizes (this scene's crop among them)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_deterministic_given_a_seed(scene, anny_model, one_thread):
    ds, _ = scene
    cfg = preset("tiny", iterations=6)
    cfg = dataclasses.replace(
        cfg, strategy=dataclasses.replace(cfg.strategy, refine_start_iter=4, refine_every=4)
    )
    a = train_avatar(ds, cfg, body=anny_model)
    b = train_avatar(ds, cfg, body=anny_model)
    assert a.losses == b.losses
    assert torch.equal(a.avatar.gaussians.means, b.avatar.gaussians.means)


def test_training_leaves_the_process_state_alone(scene, anny_model, one_thread):
    """Two runs with one seed in one process give the same avatar whatever torch's global random
    state, and a run changes neither that state nor torch's threads (they belong to the process)."""
    ds, _ = scene
    cfg = with_method(preset("tiny", iterations=6, seed=3), "eva")  # a learnable loss term too
    cfg = dataclasses.replace(
        cfg, strategy=dataclasses.replace(cfg.strategy, refine_start_iter=2, refine_every=2)
    )
    threads, rng = torch.get_num_threads(), torch.get_rng_state()
    a = train_avatar(ds, cfg, body=anny_model)
    assert torch.get_num_threads() == threads and torch.equal(torch.get_rng_state(), rng)
    torch.manual_seed(1234)
    b = train_avatar(ds, cfg, body=anny_model)
    assert a.losses == b.losses and a.refinements == b.refinements
    for name, value in a.avatar.state_dict().items():
        assert torch.equal(value, b.avatar.state_dict()[name]), name
    other = train_avatar(ds, dataclasses.replace(cfg, seed=4), body=anny_model)
    assert not torch.equal(other.avatar.gaussians.means, a.avatar.gaussians.means)


def test_checkpoints_see_the_avatar_and_their_time_is_not_training_time(scene, anny_model, lpips, one_thread):
    """The hook runs at the asked steps with the training avatar; it may evaluate it (eval mode,
    no grad) and training goes on as without it; its time is left out of train_seconds."""
    import time

    ds, _ = scene
    cfg = preset("tiny", iterations=6)
    seen = []

    metrics = ImageMetrics(lpips_alex=lpips)

    def hook(step, avatar, seconds):
        entered = time.perf_counter()
        if step == 3:
            evaluate_avatar(avatar, ds, metrics=metrics)
        time.sleep(0.4)
        seen.append((step, len(avatar.gaussians), seconds, entered, time.perf_counter()))

    started = time.perf_counter()
    hooked = train_avatar(ds, cfg, body=anny_model, checkpoint=hook, checkpoint_steps=(3, 6))
    wall = time.perf_counter() - started
    plain = train_avatar(ds, cfg, body=anny_model)
    assert [s[0] for s in seen] == [3, 6] and all(s[1] > 0 for s in seen)
    # Training seconds between the hooks: the wall time between them, the first hook's excluded.
    (_, _, at3, _, left3), (_, _, at6, entered6, _) = seen
    assert 0 < at3 < at6 <= at3 + (entered6 - left3) + 1e-3
    assert hooked.losses == plain.losses
    assert hooked.train_seconds < wall - 0.8


def test_clear_errors(scene, anny_model):
    ds, _ = scene
    no_params = dataclasses.replace(ds, params=None)
    with pytest.raises(TrainingError, match="no body parameters"):
        train_avatar(no_params, preset("tiny"), body=anny_model)
    no_train = dataclasses.replace(ds, splits={"train": [], "test_pose": [2]})
    with pytest.raises(TrainingError, match="no frames"):
        train_avatar(no_train, preset("tiny"), body=anny_model)
    with pytest.raises(ValueError, match="unknown preset"):
        preset("huge")
    with pytest.raises(ValueError, match="photometric"):
        AvatarLoss(LossConfig(photometric="nope"), lpips=None)


def test_a_non_finite_loss_stops_training_before_it_reaches_the_avatar(scene, anny_model, monkeypatch):
    """The loss turns NaN at iteration 3: training fails with a TrainingError naming it, and the
    avatar (seen through the checkpoint hook) keeps finite parameters and networks."""
    from eva_engine.train import trainer

    ds, _ = scene
    calls = []
    forward = trainer.AvatarLoss.forward

    def poisoned(self, *args, **kwargs):
        terms = forward(self, *args, **kwargs)
        calls.append(kwargs.get("step"))
        if kwargs.get("step") == 3:
            terms["total"] = terms["total"] * float("nan")
        return terms

    monkeypatch.setattr(trainer.AvatarLoss, "forward", poisoned)
    seen = []
    with pytest.raises(TrainingError, match="nan at iteration 3"):
        train_avatar(
            ds,
            preset("tiny"),
            body=anny_model,
            checkpoint=lambda step, avatar, seconds: seen.append(avatar),
            checkpoint_steps=(1,),
        )
    assert calls[-1] == 3
    avatar = seen[0]
    for name, tensor in [*avatar.gaussians.splats.items(), *avatar.named_parameters()]:
        assert torch.isfinite(tensor).all(), name


@pytest.mark.parametrize("method", ["eva", "3dgs+body"])
def test_all_empty_masks_train_and_score_finite(scene, anny_model, method, lpips):
    """A clip whose person masks are all empty (segmentation found nobody): the mask-box crop,
    the mask loss and the regions have nothing to hold, and still every number is finite."""
    ds, _ = scene
    frames = [
        dataclasses.replace(
            f, mask=torch.zeros_like(f.mask), regions={k: torch.zeros_like(v) for k, v in f.regions.items()}
        )
        for f in ds.frames
    ]
    empty = dataclasses.replace(ds, frames=frames)
    result = train_avatar(empty, with_method(preset("tiny", iterations=6), method), body=anny_model)
    assert all(torch.isfinite(torch.tensor(result.losses)))
    scores = evaluate_avatar(result.avatar, empty, metrics=ImageMetrics(lpips_alex=lpips)).regions["full"]
    assert all(torch.isfinite(torch.tensor([scores.psnr, scores.ssim, scores.lpips_vgg])))


@pytest.mark.parametrize("name", PRESETS)
def test_every_registered_preset_has_a_configuration(name):
    config = preset(name, iterations=7)
    assert config.iterations == 7 and config.strategy.refine_stop_iter > config.strategy.refine_start_iter


def test_overrides_set_nested_fields_and_refuse_unknown_ones():
    base = with_method(preset("fast"), "eva")
    config = with_overrides(
        base, ["loss.lpips_every=2", "avatar.detach_weight_inputs=true", "strategy.grow_grad2d=3e-4"]
    )
    assert config.loss.lpips_every == 2 and config.avatar.detach_weight_inputs
    assert config.strategy.grow_grad2d == 3e-4 and type(config.strategy) is type(base.strategy)
    assert config.loss.lambda_lpips == base.loss.lambda_lpips  # the rest untouched
    assert with_overrides(base, ["background=[1, 1, 1]"]).background == (1, 1, 1)
    for bad in ("avatar.nope=1", "loss", "=1"):
        with pytest.raises(ValueError):
            with_overrides(base, [bad])
    with pytest.raises(ValueError, match="lpips_every"):  # the field's own check still runs
        with_overrides(base, ["loss.lpips_every=0"])


def test_loss_terms_are_finite_and_use_the_crop(lpips):
    torch.manual_seed(0)
    h, w = 60, 50
    image = torch.rand(h, w, 3, requires_grad=True)
    alpha = torch.rand(h, w, 1, requires_grad=True)
    render = RenderOutput(
        image, alpha, torch.zeros(h, w, 1), torch.zeros(0, 2), torch.zeros(0), torch.zeros(0), 0
    )
    mask = torch.zeros(h, w)
    mask[20:30, 10:14] = 1.0  # a box smaller than LPIPS's minimum: grown to 32 px
    target = torch.rand(h, w, 3)
    loss = AvatarLoss(LossConfig(), lpips=lpips)
    x0, y0, x1, y1 = loss.person_box(mask)
    assert (x1 - x0, y1 - y0) == (32, 32)  # the mask's box, padded by 4, grown to min_crop
    terms = loss(render, target, mask)
    assert set(terms) == {"photometric", "mask", "ssim", "lpips", "total"}
    terms["total"].backward()
    assert torch.isfinite(image.grad).all() and torch.isfinite(alpha.grad).all()
    # SSIM / LPIPS only see the crop: pixels far outside the box get only the L1 gradient, which
    # weighs each pixel as a mean over the person's box does (the official code's scale).
    l1_grad = 1.0 / (32 * 32 * 3)
    assert torch.allclose(image.grad[h - 1, w - 1].abs(), torch.full((3,), l1_grad))
    # "frame" normalisation: a mean over the frame; 3DGS's 0.8 weight scales the L1 gradient.
    image.grad = None
    frame = AvatarLoss(LossConfig(pixel_norm="frame", lambda_photometric=0.8), lpips=lpips)
    frame(render, target, mask)["total"].backward()
    assert torch.allclose(image.grad[h - 1, w - 1].abs(), torch.full((3,), 0.8 / (h * w * 3)))
    with pytest.raises(ValueError, match="pixel_norm"):
        LossConfig(pixel_norm="box")
    # Degenerate: an empty mask (person out of view) still gives finite terms.
    terms = AvatarLoss(LossConfig(), lpips=lpips)(render, target, torch.zeros(h, w))
    assert all(torch.isfinite(v) for v in terms.values())


def test_lpips_every_k_steps_keeps_its_expected_weight(lpips):
    torch.manual_seed(0)
    h, w = 48, 40
    image = torch.rand(h, w, 3, requires_grad=True)
    render = RenderOutput(
        image, torch.rand(h, w, 1), torch.zeros(h, w, 1), torch.zeros(0, 2), torch.zeros(0), torch.zeros(0), 0
    )
    mask, target = torch.ones(h, w), torch.rand(h, w, 3)
    every = AvatarLoss(LossConfig(lpips_every=3), lpips=lpips)
    always = AvatarLoss(LossConfig(), lpips=lpips)
    reference = always(render, target, mask)
    on, off = every(render, target, mask, step=6), every(render, target, mask, step=7)
    assert "lpips" in on and "lpips" not in off
    torch.testing.assert_close(on["lpips"], reference["lpips"])
    # 3 lambda_l on one step in three: the same LPIPS weight per step on average.
    lam = LossConfig().lambda_lpips
    torch.testing.assert_close(on["total"] - off["total"], 3 * lam * reference["lpips"])
    torch.testing.assert_close(every(render, target, mask)["total"], reference["total"])  # no step: always
    # Thinned from step 300 on only: every step before it at its own weight.
    late = AvatarLoss(LossConfig(lpips_every=3, lpips_every_from=300), lpips=lpips)
    for step in (7, 299):
        torch.testing.assert_close(late(render, target, mask, step=step)["total"], reference["total"])
    assert "lpips" not in late(render, target, mask, step=301)
    torch.testing.assert_close(late(render, target, mask, step=300)["total"], on["total"])
    with pytest.raises(ValueError, match="lpips_every"):
        LossConfig(lpips_every=0)
    with pytest.raises(ValueError, match="lpips_every_from"):
        LossConfig(lpips_every_from=-1)


def test_the_lpips_loss_network_is_chosen_by_config(lpips):
    assert AvatarLoss(LossConfig(lpips_net="vgg")).lpips.net == "vgg"
    assert AvatarLoss(LossConfig(), lpips=lpips).lpips.net == "alex"
    with pytest.raises(ValueError, match="LPIPS-vgg"):
        AvatarLoss(LossConfig(lpips_net="vgg"), lpips=lpips)  # a metric network of the wrong kind
    with pytest.raises(ValueError, match="lpips_net"):
        LossConfig(lpips_net="squeeze")


def test_official_rates_per_network_and_the_means_decay_horizon(anny_model):
    """The official recipe's rates: the weight-offset MLP 5e-5, the pose refiner 5e-6 for the
    body and 0.05 x that for hands and face; the means decay over 30,000 steps, not the run."""
    config = with_method(preset("default"), "eva-official")
    avatar = Avatar.create(anny_model, anny_model.shape_defaults, config.avatar)
    loss = AvatarLoss(dataclasses.replace(config.loss, lambda_lpips=0.0))
    mlps = make_extra_optimizers(avatar, config, loss)[0]
    rates = {id(p): g["lr"] for g in mlps.param_groups for p in g["params"]}
    refiner = avatar.pose_refiner.mlps
    assert {rates[id(p)] for p in refiner["body"].parameters()} == {5e-6}
    for part in ("hand", "face"):
        got = [rates[id(p)] for p in refiner[part].parameters()]
        assert got == pytest.approx([2.5e-7] * len(got))
    assert {rates[id(p)] for p in avatar.weight_offsets.parameters()} == {5e-5}
    # 3DGS's horizon: a 2,000-step run ends at 1.6e-4 * 0.01^(2000/30000) ~ 1.18e-4.
    assert means_lr(config, 2000) == pytest.approx(1.6e-4 * 0.01 ** (2000 / 30000), rel=1e-6)
    assert means_lr(preset("default"), 1999) == pytest.approx(1.6e-6, rel=1e-6)  # the run's own
    with pytest.raises(ValueError, match="means_lr_steps"):
        OptimConfig(means_lr_steps=0)


def test_the_trainer_visits_a_blinking_frame_more_often(scene, anny_model):
    """``TrainConfig.expression_events`` (``train/frame_order.py``): a frame with a fitted blink
    comes back ``repeats`` more times per epoch; without it, every frame once."""
    ds, _ = scene
    train = list(ds.splits["train"])
    blink = anny_model.expression_names.index("eyeBlinkLeft")
    params = ds.params
    expression = params.expression.clone()
    expression[train[0], blink] = 0.8
    blinking = dataclasses.replace(ds, params=dataclasses.replace(params, expression=expression))
    config = dataclasses.replace(
        preset("tiny", iterations=2), expression_events=ExpressionEventsConfig(repeats=4)
    )
    run = TrainingRun(blinking, config, anny_model, torch.device("cpu"))
    assert sorted(run.epoch) == sorted([*range(len(train)), 0, 0, 0, 0])
    plain = TrainingRun(blinking, preset("tiny", iterations=2), anny_model, torch.device("cpu"))
    assert plain.epoch == list(range(len(train)))


def test_the_trainer_seats_the_gaussians_on_the_training_frames_median_face(scene, anny_model):
    """``AvatarConfig.template_expression="median"``: the template is the body with the training
    frames' median expression (a person whose eyes are wider open than the model's most of the
    time gets a template with its lids raised); the default keeps the zero expression."""
    ds, _ = scene
    train = list(ds.splits["train"])
    wide = anny_model.expression_names.index("eyeWideLeft")
    expression = ds.params.expression.clone()
    expression[train, wide] = torch.linspace(0.2, 0.8, len(train))
    widened = dataclasses.replace(ds, params=dataclasses.replace(ds.params, expression=expression))
    tiny = preset("tiny", iterations=2)
    median = dataclasses.replace(tiny, avatar=dataclasses.replace(tiny.avatar, template_expression="median"))
    run = TrainingRun(widened, median, anny_model, torch.device("cpu"))
    face = expression[train].median(dim=0).values
    torch.testing.assert_close(run.avatar.template_expression, face.to(run.avatar.template_expression))
    plain = TrainingRun(widened, tiny, anny_model, torch.device("cpu"))
    assert not bool(plain.avatar.template_expression.any())
