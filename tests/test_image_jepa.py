"""The image-JEPA recipe: config checks, loss choice, reproducible and resumable training,
and the evaluation protocol (frozen features of un-augmented images at ``eval_image_size``)."""

import copy
import dataclasses
import math

import pytest
import torch
from torch import nn

from ebjepa_tutorial import augment, losses
from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.evaluation import classify
from ebjepa_tutorial.training import image
from ebjepa_tutorial.training.image import ImageJEPAConfig
from research import train_image

TINY = ImageJEPAConfig(widths=(4, 4, 8, 8), projector=(16, 16), batch_size=8, steps=4,
                       warmup_steps=1, image_size=16)


def _images(n=32, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, 3, 32, 32), dtype=torch.uint8, generator=generator)


class ShapeRecorder(nn.Module):
    """A stand-in encoder: ``(B, 3, S, S) -> (B, 4)`` by average pool and a linear layer.

    It keeps every batch it is given, to check what the evaluation feeds it.
    """

    def __init__(self):
        super().__init__()
        self.linear = nn.Linear(3, 4)
        self.inputs = []

    def forward(self, x):
        self.inputs.append(x.clone())
        return self.linear(x.mean(dim=(2, 3)))


def test_the_method_names_the_loss():
    assert [ImageJEPAConfig(loss=loss).method for loss in (image.VICReg(), image.SIGReg(), None)
            ] == ["vicreg", "sigreg", "invariance"]


def test_evaluation_is_at_the_native_32_px_whatever_the_training_size():
    assert ImageJEPAConfig().eval_image_size == 32
    for notebook in ("01", "02"):
        for scale in ("class", "full"):  # ci probes at 16 px: it only checks that code runs
            assert preset(notebook, scale).config.eval_image_size == 32, (notebook, scale)
        assert preset(notebook, "ci").config.eval_image_size == 16
    assert preset("01", "class").config.image_size == 16  # trained small, probed at 32 px


@pytest.mark.parametrize("loss, terms", [
    (image.VICReg(), {"invariance", "variance", "covariance"}),
    (image.SIGReg(slices=8), {"invariance", "sigreg"}),
    (None, {"invariance", "variance", "covariance"}),  # logged, with zero weight
])
def test_each_loss_logs_its_terms(loss, terms):
    config = dataclasses.replace(TINY, loss=loss, steps=2, warmup_steps=0)
    _, history = image.train_image_jepa(config, _images(), progress=False)
    assert set(history) == {"step", "loss"} | terms
    assert all(math.isfinite(value) for value in history["loss"])
    if loss is None:  # the regularisers are only watched: the loss is the invariance alone
        assert history["loss"] == pytest.approx(history["invariance"], rel=1e-6)


def test_one_block_per_stage_makes_a_resnet_10_and_resnet_18_runs_keep_their_identity():
    def blocks(config):
        return [len(stage) for stage in image.ImageJEPA(config).encoder.stages]

    shallow = dataclasses.replace(TINY, blocks_per_stage=1)
    assert blocks(TINY) == [2, 2, 2, 2] and blocks(shallow) == [1, 1, 1, 1]
    assert image.identity(shallow)["blocks_per_stage"] == 1
    # files of ResNet-18 runs, saved before the block count existed, are still recognised
    assert "blocks_per_stage" not in image.identity(TINY)


def test_model_shapes_with_and_without_projector():
    model = image.ImageJEPA(TINY)
    assert model(torch.randn(2, 3, 16, 16)).shape == (2, 16)
    bare = image.ImageJEPA(ImageJEPAConfig(widths=(4, 4, 8, 8), projector=None))
    assert bare(torch.randn(2, 3, 16, 16)).shape == (2, 8)


def test_training_is_reproducible_and_resumable(tmp_path, monkeypatch):
    images = _images()
    straight, history = image.train_image_jepa(TINY, images, progress=False)
    again, _ = image.train_image_jepa(TINY, images, progress=False)
    assert all(torch.equal(p, q) for p, q in zip(straight.parameters(), again.parameters()))

    # A kernel that dies while making the views of step 2 ...
    calls, real_two_views = [], image.augment.two_views

    def dying_two_views(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real_two_views(*args, **kwargs)

    ckpt = tmp_path / "run.pt"
    monkeypatch.setattr(image.augment, "two_views", dying_two_views)
    monkeypatch.setattr(image, "CHECKPOINT_EVERY", 1)
    with pytest.raises(KeyboardInterrupt):
        image.train_image_jepa(TINY, images, checkpoint=ckpt, progress=False)
    monkeypatch.undo()
    # ... then a new run picks up at step 2 and ends where the uninterrupted run ended.
    resumed, history2 = image.train_image_jepa(TINY, images, checkpoint=ckpt,
                                                    progress=False)
    assert history2["step"] == history["step"]
    assert history2["loss"] == pytest.approx(history["loss"], rel=1e-5)
    for p, q in zip(straight.parameters(), resumed.parameters()):
        assert torch.allclose(p, q, atol=1e-6)


def test_probe_encoder_reports_both_accuracies():
    images, labels = _images(40), torch.arange(40) % 4
    model = image.ImageJEPA(TINY)
    result = classify.probe_encoder(model.encoder, TINY, (images, labels), (images, labels))
    assert set(result) == {"probe_acc", "knn_acc"}
    assert 0.0 <= result["probe_acc"] <= 1.0


def test_cached_probe_scores_are_reused_only_for_the_same_encoder_and_data(
        tmp_path, monkeypatch):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    images, labels = _images(40), torch.arange(40) % 4
    encoder = image.ImageJEPA(TINY).encoder
    first = classify.probe_encoder(encoder, TINY, (images, labels), (images, labels), cache=True)
    assert len(list((tmp_path / "probes").glob("*.json"))) == 1

    def no_probe(*args, **kwargs):
        raise AssertionError("the probe ran again")

    monkeypatch.setattr(classify, "linear_probe", no_probe)
    assert classify.probe_encoder(encoder, TINY, (images, labels), (images, labels),
                                  cache=True) == first  # read back, not recomputed
    with pytest.raises(AssertionError, match="the probe ran again"):  # other test labels
        classify.probe_encoder(encoder, TINY, (images, labels), (images, labels.flip(0)),
                               cache=True)
    with torch.no_grad():
        next(encoder.parameters()).add_(0.01)
    with pytest.raises(AssertionError, match="the probe ran again"):  # other weights
        classify.probe_encoder(encoder, TINY, (images, labels), (images, labels), cache=True)


@pytest.mark.parametrize("eval_size", [32, 24, 16])
def test_probe_and_knn_see_images_of_eval_image_size(eval_size):
    config = dataclasses.replace(TINY, eval_image_size=eval_size)  # trained on 16-px views
    encoder = ShapeRecorder()
    train, test = _images(40), _images(20, seed=1)
    classify.probe_encoder(encoder, config, (train, torch.arange(40) % 4),
                             (test, torch.arange(20) % 4))
    assert {tuple(x.shape[1:]) for x in encoder.inputs} == {(3, eval_size, eval_size)}
    assert sum(len(x) for x in encoder.inputs) == 40 + 20  # every image once, none augmented
    if eval_size == 32:  # CIFAR-10's own size: normalised, not resampled
        seen = torch.cat(encoder.inputs)
        assert torch.equal(seen, augment.normalize(torch.cat([train, test])))


def test_a_resnet_takes_any_image_size():
    # the global average pool is what lets a network trained on 16 px be probed at 32 px
    encoder = image.ImageJEPA(TINY).encoder.eval()
    for size in (16, 32):
        assert classify.embed(encoder, _images(4), size).shape == (4, encoder.out_dim)


def test_protocol_names_both_sizes():
    from research.train_image import protocol

    words = protocol(TINY)
    assert "32-px images (their native size, no resizing)" in words
    assert "trained on 16-px views" in words
    assert "resized from 32 px" in protocol(
        dataclasses.replace(TINY, eval_image_size=16))


def test_train_or_load_trains_once_then_loads(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    images = _images()
    first, history = image.train_or_load(TINY, "tiny_run", images)
    assert "Trained and saved" in capsys.readouterr().out
    assert not (tmp_path / "checkpoints" / "tiny_run.partial").exists()
    again, history2 = image.train_or_load(TINY, "tiny_run", images)
    assert "Loaded" in capsys.readouterr().out
    assert history2 == history and not again.training
    assert all(torch.equal(p, q) for p, q in zip(first.parameters(), again.parameters()))


def test_checkpoints_do_not_depend_on_the_evaluation_size(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    images = _images()
    assert "eval_image_size" not in image.identity(TINY)
    image.train_or_load(TINY, "tiny_run", images)
    capsys.readouterr()
    image.train_or_load(dataclasses.replace(TINY, eval_image_size=24), "tiny_run", images)
    assert "Loaded" in capsys.readouterr().out  # probing at another size is the same run
    image.train_or_load(dataclasses.replace(TINY, image_size=8), "tiny_run", images)
    assert "Trained and saved" in capsys.readouterr().out  # training at another size is not


def test_train_or_load_can_keep_only_the_encoder(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    images = _images()
    model, _ = image.train_or_load(TINY, "tiny_run", images)
    encoder, history = image.train_or_load(TINY, "tiny_encoder", images, encoder_only=True)
    assert "Trained and saved" in capsys.readouterr().out
    assert all(torch.equal(p, q) for p, q in zip(model.encoder.parameters(), encoder.parameters()))
    stored = torch.load(tmp_path / "checkpoints" / "tiny_encoder.pt", weights_only=False)
    assert set(stored["model"]) == set(encoder.state_dict())  # no projector weights
    again, history2 = image.train_or_load(TINY, "tiny_encoder", images, encoder_only=True)
    assert "Loaded" in capsys.readouterr().out and history2 == history and not again.training
    # the training time comes back with the run: chapter 02 puts its runs on this clock
    assert history.seconds > 0 and history2.seconds == pytest.approx(history.seconds)
    image.train_or_load(TINY, "tiny_encoder", images)  # a whole-model run of that name
    assert "another configuration" in capsys.readouterr().out  # never reads encoder weights


def test_a_run_given_the_images_with_their_labels_is_told_to_pass_the_images(tmp_path,
                                                                             monkeypatch):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    pair = _images(), torch.zeros(8, dtype=torch.long)
    with pytest.raises(ValueError, match=r"no image tensor to train it on \(got tuple\): pass "
                                         r"load_cifar10\('train'\)\[0\], the images without"):
        image.train_or_load(TINY, "tiny_pair", pair)


def test_long_run_command_writes_a_float16_encoder(tmp_path, monkeypatch, capsys):
    train = _images(40), torch.arange(40) % 4
    monkeypatch.setattr("research.train_image.load_cifar10", lambda split: train)
    monkeypatch.setattr(
        "research.train_image.preset", lambda notebook, scale: dataclasses.replace(
        preset("01", "ci"), config=TINY, long_config=TINY, train_images=40, test_images=40))
    # trains on the best device there is (a GPU: the full scale is the paper's run); the
    # stand-in "cpu:0" is a device of its own, the CPU by another name
    monkeypatch.setattr("research.launch.get_device", lambda: torch.device("cpu:0"))
    devices, real_train = [], train_image.train_image_jepa

    def recording_train(*args, device, **kwargs):
        devices.append(device)
        return real_train(*args, device=device, **kwargs)

    monkeypatch.setattr(train_image, "train_image_jepa", recording_train)
    out = tmp_path / "long.pt"
    train_image.main(["--loss", "vicreg", "--steps", "6", "--out", str(out)])
    assert devices == [torch.device("cpu:0")]
    stored = torch.load(out, weights_only=False)
    assert stored["config"] == image.identity(dataclasses.replace(TINY, steps=6), encoder_only=True)
    assert all(v.dtype == torch.float16 for v in stored["model"].values() if v.is_floating_point())
    assert 0 <= stored["probe_acc"] <= 1 and not out.with_suffix(".partial").exists()
    assert "linear probe" in capsys.readouterr().out


def test_long_presets_train_longer_than_the_main_run():
    for notebook in ("01", "02"):
        cfg = preset(notebook, "class")
        assert cfg.long_config.steps > cfg.config.steps
        assert cfg.long_config.method == cfg.config.method  # SIGReg's lambda may differ
        full = preset(notebook, "full")
        assert full.long_config == full.config  # the paper's run is already the long one


@pytest.mark.slow  # the full-width ResNet-18
@pytest.mark.parametrize("notebook, projector", [("01", (2048, 2048)), ("02", (2048, 128))])
def test_full_scale_is_the_papers_recipe_and_takes_a_step(notebook, projector):
    config = preset(notebook, "full").config
    epoch = 50_000 // 256  # optimiser steps per CIFAR-10 epoch at batch 256
    assert (config.widths, config.image_size, config.eval_image_size) == ((64, 128, 256, 512),
                                                                          32, 32)
    assert (config.batch_size, config.steps, config.warmup_steps) == (256, 300 * epoch,
                                                                      10 * epoch)
    assert config.projector == projector
    if notebook == "01":  # the paper's 1 / 1 / 80, in this course's averaged convention
        assert config.loss == image.VICReg(1.0, 2.0, 160.0)
    else:  # lambda 10 on the statistic without the factor N, as the paper's code
        assert config.loss == image.SIGReg(10.0, scale_by_n=False)
    # one step of the full-width network on a small batch: the recipe runs unchanged
    model, history = image.train_image_jepa(
        dataclasses.replace(config, batch_size=4, steps=2, warmup_steps=1), _images(8),
        progress=False)
    assert model.encoder.out_dim == 512 and all(map(math.isfinite, history["loss"]))


def test_long_run_command_refuses_bad_steps_before_loading_data(monkeypatch, capsys):
    def no_data(split):
        raise AssertionError("the data was loaded before the arguments were checked")

    monkeypatch.setattr("research.train_image.load_cifar10", no_data)
    with pytest.raises(SystemExit):
        train_image.main(["--steps", "100", "--out", "x.pt"])  # class warm-up is 200 steps
    assert "warmup_steps must be an int in 0..steps-1" in capsys.readouterr().err


def test_long_run_command_takes_a_scale_and_counts_resumed_minutes(tmp_path, monkeypatch):
    train = _images(40), torch.arange(40) % 4
    monkeypatch.setattr("research.train_image.load_cifar10", lambda split: train)
    asked = []

    def sizes(notebook, scale):
        asked.append(scale)
        return dataclasses.replace(preset("01", "ci"), config=TINY, train_images=40,
                                   test_images=40)

    monkeypatch.setattr("research.train_image.preset", sizes)
    clock = iter(range(0, 10_000, 30))  # every reading of the clock: 30 s later
    monkeypatch.setattr("ebjepa_tutorial.training.loop.time.perf_counter", lambda: next(clock))
    out = tmp_path / "long.pt"
    partial = out.with_suffix(".partial")
    image.train_image_jepa(dataclasses.replace(TINY, steps=6), train[0], checkpoint=partial)
    train_image.main(["--scale", "ci", "--steps", "6", "--out", str(out)])  # resumes: all done
    assert asked == ["ci"]
    assert torch.load(out, weights_only=True)["minutes"] == 3.0  # 6 steps of 30 s, not 0


def test_the_default_weights_are_the_reference_codes_with_the_views_averaged():
    # the EB-JEPA code adds the two views' regularisers with weights 1 / 1 / 80; the course
    # averages them, so the same loss needs 1 / 2 / 160 (a copied 1 / 1 / 80 halves both)
    gen = torch.Generator().manual_seed(0)
    z_a, z_b = torch.randn(32, 8, generator=gen), torch.randn(32, 8, generator=gen) * 0.5
    weights = image.VICReg()
    ours, _ = losses.vicreg_loss(z_a, z_b, weights.inv_coeff, weights.std_coeff,
                                 weights.cov_coeff)
    reference = (losses.invariance_term(z_a, z_b)
                 + 1.0 * (losses.variance_term(z_a) + losses.variance_term(z_b))
                 + 80.0 * (losses.covariance_term(z_a) + losses.covariance_term(z_b)))
    assert torch.allclose(ours, reference, rtol=1e-6)


def _record_steps(config, record):
    """Train ``config`` on 32 random images with the package's step, calling ``record(batch,
    optimizer)`` before each step."""
    def recording(net, batch, optimizer, scheduler, weights):
        record(batch, optimizer)
        return image.package_step(config)(net, batch, optimizer, scheduler, weights)

    return image.train_image_jepa(config, _images(), progress=False, step=recording)


def test_the_optimiser_warms_up_then_follows_a_cosine_and_spares_1d_params_weight_decay():
    """The run's AdamW: every group's rate rises linearly over ``warmup_steps`` to ``LR``, then
    follows a half cosine down to 0 at the last step; weight decay falls on the weight
    matrices only, never on biases or batch-norm parameters."""
    rates, groups = [], []

    def record(batch, optimizer):
        rates.append([group["lr"] for group in optimizer.param_groups])
        groups.append([(group["weight_decay"], {p.ndim > 1 for p in group["params"]})
                       for group in optimizer.param_groups])

    _record_steps(dataclasses.replace(TINY, steps=4, warmup_steps=2), record)
    # warm-up: 1/2, 1; cosine from step 1 (the peak) to step 3: halfway at step 2, then 0
    lr = image.LR
    assert [r for step in rates for r in step] == pytest.approx([lr / 2] * 2 + [lr] * 2
                                                                + [lr / 2] * 2 + [0.0] * 2)
    assert groups[0] == [(image.WEIGHT_DECAY, {True}), (0.0, {False})]


def test_every_step_trains_on_a_batch_of_its_own():
    """Step n's views come from its own draw of images and augmentations: no two steps of a
    run see the same batch (a run repeating one batch still trains, on 1/steps of the data)."""
    views = []
    _record_steps(dataclasses.replace(TINY, steps=4), lambda batch, _: views.append(batch[0][0]))
    assert len(views) == 4
    assert not any(torch.equal(views[i], views[j]) for i in range(4) for j in range(i))


def test_all_views_passes_each_view_through_the_model_on_its_own():
    """``AllViews`` runs the model once per view, so batch norm normalises each view over its
    own batch, exactly as two separate calls would (one pass over both views mixes their
    statistics)."""
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4)).train()
    a, b = torch.randn(8, 3), 3 * torch.randn(8, 3) + 1
    reference = copy.deepcopy(model)
    out_a, out_b = image.AllViews(model)(a, b)
    assert torch.allclose(out_a, reference(a), atol=1e-6)
    assert torch.allclose(out_b, reference(b), atol=1e-6)


def test_resize_averages_detail_finer_than_its_new_pixels():
    """Downsizing is antialiased: a bright row every 4 rows, shrunk from 32 to 8 px, becomes an
    even grey a quarter of the way to white (plain bilinear sampling falls between the
    stripes and loses them, black all over)."""
    images = torch.zeros(1, 3, 32, 32, dtype=torch.uint8)
    images[..., ::4, :] = 255
    black = augment.normalize(torch.zeros(1, 3, 1, 1, dtype=torch.uint8))
    white = augment.normalize(torch.full((1, 3, 1, 1), 255, dtype=torch.uint8))
    share = (image.resize(images, 8) - black) / (white - black)  # 0 black, 1 white
    assert torch.allclose(share[..., 1:-1, :], torch.full((1, 3, 6, 8), 0.25), atol=1e-4)
