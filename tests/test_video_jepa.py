"""Video JEPA (chapter 03): shapes, the multistep losses by hand, the checker, probe, errors."""

import copy
from dataclasses import replace

import pytest
import torch

from ebjepa_tutorial import viz
from ebjepa_tutorial.course.exercises import ExerciseError
from ebjepa_tutorial.course.exercises.video import check_parallel_rollout_loss
from ebjepa_tutorial.data.moving_mnist import centres_to_grid, generate_moving_mnist
from ebjepa_tutorial.evaluation.detection import (
    check_clips,
    detection_report,
    evaluation_clips,
    fit_detection_probe,
    grid_features,
)
from ebjepa_tutorial.evaluation.metrics import average_precision
from ebjepa_tutorial.losses.rollout import (
    parallel_rollout_loss,
    parallel_unroll,
    rollout,
    rollout_loss,
)
from ebjepa_tutorial.models.video import (
    VIDEO_MODEL_CONFIGS,
    VideoJEPA,
    VideoModelConfig,
    detection_head,
    frame_decoder,
)
from ebjepa_tutorial.training import video as video_training
from ebjepa_tutorial.training.checkpoints import load_checkpoint
from ebjepa_tutorial.training.video import (
    PAPER_RECIPE,
    VIDEO_CONFIGS,
    ablation_configs,
    run_name,
    video_jepa_step,
)
from research import train_video
from research.from_notebook import definitions

NOTEBOOK = definitions("03_video_jepa.ipynb", "train_video_jepa", "train_or_load", "fit_decoder")


def train_video_jepa(config, clips, **options):
    """Notebook 03's loop with the course's step (the package's copy of the cell's)."""
    return NOTEBOOK.train_video_jepa(config, clips, video_jepa_step, **options)


def train_or_load(config, name, train_digits, device=None):
    """Notebook 03's train_or_load with the course's step."""
    return NOTEBOOK.train_or_load(config, name, train_digits, video_jepa_step, device)


CI = VIDEO_CONFIGS["ci"]


@pytest.fixture(scope="module")
def digits():
    """Stand-in digits: a filled 10x10 square in a 28x28 patch (the model never sees MNIST here)."""
    patches = torch.zeros(8, 1, 28, 28, dtype=torch.uint8)
    patches[:, :, 9:19, 9:19] = 255
    return patches


def shift_predictor(c):
    """The last latent plus ``c``: order k of a rollout is ``z_last + k c``."""
    return lambda window: window[:, -1] + c


@pytest.mark.parametrize("scale", ["ci", "class", "full"])
def test_shapes(scale):
    config = VIDEO_MODEL_CONFIGS[scale]
    model = VideoJEPA(config).eval()
    c, s = config.latent_channels, config.latent_side
    assert s == {"ci": 8, "class": 8, "full": 64}[scale]
    with torch.no_grad():
        z = model.encode(torch.randint(0, 256, (2, 3, 1, 64, 64), dtype=torch.uint8))
        assert z.shape == (2, 3, c, s, s)
        assert model.predictor(z[:, :2]).shape == (2, c, s, s)
        assert model.project(z).shape == (2 * 3 * s * s, config.projector_dim)
        assert detection_head(c)(z[:, 0]).shape == (2, 8, 8)
        assert frame_decoder(c, s)(z[:, 0]).shape == (2, 1, 64, 64)


def test_stem_stride_halves_the_frame_before_the_blocks():
    config = VideoModelConfig(stem_stride=2, strides=(1, 2, 2), predictor_levels=2)
    assert config.latent_side == 8
    encoder = VideoJEPA(config).encoder
    assert encoder.stem[0].stride == (2, 2)
    assert encoder(torch.zeros(3, 1, 64, 64)).shape == (3, config.latent_channels, 8, 8)


def test_channels_last_gives_the_class_encoders_convolutions_the_same_gradients():
    # PyTorch's CPU backward in channels_last crashes on some strided 1x1 convolutions
    # (the ci encoder's, at 64x64): check each convolution of the class encoder, at the
    # shape it sees in training, against the default layout
    encoder = VideoJEPA(VIDEO_CONFIGS["class"].model).encoder
    convs = {name: m for name, m in encoder.named_modules() if isinstance(m, torch.nn.Conv2d)}
    shapes = {}

    def remember(name):  # a forward hook that notes the input's shape
        def hook(module, args, out):
            shapes[name] = args[0].shape
        return hook

    hooks = [conv.register_forward_hook(remember(name)) for name, conv in convs.items()]
    encoder(torch.rand(4, 1, 64, 64))
    for hook in hooks:
        hook.remove()
    for name, conv in convs.items():
        x = torch.randn(shapes[name])
        grads = []
        for layout in (torch.contiguous_format, torch.channels_last):
            layer = copy.deepcopy(conv).to(memory_format=layout)
            xi = x.clone(memory_format=layout).requires_grad_()
            out = layer(xi)
            out.backward(torch.linspace(-1, 1, out.numel()).view_as(out))
            grads.append(torch.cat([xi.grad.flatten(), layer.weight.grad.flatten()]))
        assert (grads[0] - grads[1]).norm() < 1e-5 * grads[0].norm(), name  # summation order


def test_residual_predictor_starts_as_copy_of_last_latent():
    model = VideoJEPA(VIDEO_MODEL_CONFIGS["ci"]).eval()
    window = torch.randn(3, 2, 8, 8, 8)
    assert torch.equal(model.predictor(window), window[:, -1])


def test_rollout_loss_by_hand():
    # z_t = t everywhere: the true latent moves by 1 per frame. "last + c" predicts
    # z_{s+1} + k c for the frame z_{s+1+k} = z_{s+1} + k, so the error of order k is k (1 - c).
    z = torch.arange(8.0).view(1, 8, 1, 1, 1).expand(2, 8, 3, 2, 2)
    for c in (0.0, 0.5, 1.0):
        expected = (1 - c) ** 2 * (1 + 4 + 9) / 3  # mean over k = 1, 2, 3 of (k (1 - c))^2
        got = rollout_loss(shift_predictor(c), z, context=2, steps=3)
        assert got.shape == ()
        assert got.item() == pytest.approx(expected)
    # teacher forcing would see the true z_{s+k} and always be off by exactly 1 - c = 1
    assert rollout_loss(shift_predictor(0.0), z, steps=1).item() == pytest.approx(1.0)


def test_parallel_rollout_loss_by_hand():
    # z_t = t, "last + c": after step k frame t is predicted min(k, t - 1) steps past its
    # most recent true latent (frames 0 and 1 are fed back true), so its error is that times
    # (1 - c). Frames 2..5, steps 1..3: errors 1 1 1 1 / 1 2 2 2 / 1 2 3 3.
    z = torch.arange(6.0).view(1, 6, 1, 1, 1).expand(2, 6, 3, 2, 2)
    for c in (0.0, 0.5):
        expected = (1 - c) ** 2 * (4 / 4 + 13 / 4 + 23 / 4) / 3
        got = parallel_rollout_loss(shift_predictor(c), z, context=2, steps=3)
        assert got.item() == pytest.approx(expected)


def test_parallel_step_k_predicts_k_steps_past_the_newest_true_latent():
    # A predictor that adds its window: an impulse at true frame j reaches exactly the
    # predictions that depend on it. Step k's frame t (t >= context - 1 + k) depends on
    # frames t - 2k .. t - k, so on nothing newer than t - k, unlike the autoregressive
    # rollout, whose order-k window holds one true latent only at k = 1.
    context, steps, T = 2, 3, 10
    for j in range(T):
        z = torch.zeros(1, T, 1, 1, 1)
        z[:, j] = 1.0
        for k, predictions in enumerate(parallel_unroll(lambda w: w.sum(1), z, context, steps), 1):
            for t in range(context - 1 + k, T):
                reached = predictions[0, t - context].item() > 0
                assert reached == (t - 2 * k <= j <= t - k), (j, k, t)


def test_both_unrolls_are_the_same_loss_at_one_step():
    g = torch.Generator().manual_seed(0)
    z = torch.randn(2, 7, 3, 2, 2, generator=g)
    weight = torch.randn(2, 3, 3, generator=g)
    predictor = lambda w: torch.tanh(torch.einsum("nkchw,kcd->ndhw", w, weight))  # noqa: E731
    one_step = rollout_loss(predictor, z, steps=1)
    assert torch.equal(parallel_rollout_loss(predictor, z, steps=1), one_step)
    assert not torch.allclose(parallel_rollout_loss(predictor, z, steps=3),
                              rollout_loss(predictor, z, steps=3))


@pytest.mark.parametrize("loss", [rollout_loss, parallel_rollout_loss])
def test_detached_later_orders_keep_the_value_and_give_the_encoder_one_step_only(loss):
    g = torch.Generator().manual_seed(1)
    z0 = torch.randn(2, 8, 3, 2, 2, generator=g)
    weight = torch.randn(2, 3, 3, generator=g) / 2
    predictor = lambda w: torch.tanh(torch.einsum("nkchw,kcd->ndhw", w, weight))  # noqa: E731
    steps, n = 3, 8 - 2 - 3 + 1  # rollout_loss's order-1 term covers n starts

    def value_and_grad(fn):
        z = z0.clone().requires_grad_()
        value = fn(z)
        return value.detach(), torch.autograd.grad(value, z)[0]

    full, full_grad = value_and_grad(lambda z: loss(predictor, z, steps=steps))
    value, grad = value_and_grad(lambda z: loss(predictor, z, steps=steps, detach_later=True))
    frames = n + 2 if loss is rollout_loss else 8
    _, one_step_grad = value_and_grad(lambda z: loss(predictor, z[:, :frames], steps=1) / steps)
    assert torch.allclose(value, full)
    assert torch.allclose(grad, one_step_grad) and not torch.allclose(grad, full_grad)


def test_rollout_feeds_predictions_back():
    window = torch.zeros(1, 2, 1, 1, 1)
    window[:, 1] = 1.0
    out = rollout(lambda w: 2 * w[:, -1] - w[:, -2], window, steps=3)  # constant velocity
    assert out.flatten().tolist() == [2.0, 3.0, 4.0]


def test_checker_accepts_the_loss_and_rejects_wrong_answers(capsys):
    def mine(predictor, z, context=2, steps=4, detach_later=False):  # a learner's correct copy
        return parallel_rollout_loss(predictor, z, context, steps, detach_later)

    assert check_parallel_rollout_loss(mine) is mine
    assert "Correct" in capsys.readouterr().out

    def teacher_forcing(predictor, z, context=2, steps=4, detach_later=False):
        return parallel_rollout_loss(predictor, z, context, 1)  # K copies of step 1

    def context_two(predictor, z, context=2, steps=4, detach_later=False):
        return parallel_rollout_loss(predictor, z, 2, steps, detach_later)

    def ignores_detach_later(predictor, z, context=2, steps=4, detach_later=False):
        return parallel_rollout_loss(predictor, z, context, steps)

    for wrong, mistake in [(teacher_forcing, "teacher forcing"),
                           (context_two, "ignored the context argument"),
                           (ignores_detach_later, "steps 2..K still reach the encoder")]:
        with pytest.raises(ExerciseError, match=mistake):
            check_parallel_rollout_loss(wrong)


def test_detection_probe_on_separable_latents():
    g = torch.Generator().manual_seed(0)
    centres = torch.rand(64, 2, 2, generator=g) * 64  # two digit centres per frame
    targets = centres_to_grid(centres)  # (64, 8, 8)
    noise = torch.randn(64, 1, 8, 8, generator=g)
    features = torch.cat([targets[:, None] * 10, noise], dim=1)  # channel 0 marks the centres
    torch.manual_seed(7)
    probe = fit_detection_probe(features, targets, steps=50)
    after = torch.rand(3)
    torch.manual_seed(7)
    assert torch.equal(after, torch.rand(3))  # the caller's random draws go on untouched
    with torch.no_grad():
        assert average_precision(probe(features), targets) > 0.99
    again = fit_detection_probe(features, targets, steps=50)  # seeded: the same head
    assert all(torch.equal(a, b) for a, b in zip(probe.parameters(), again.parameters()))


def test_bad_inputs_raise_clear_errors():
    z = torch.randn(2, 5, 3, 2, 2)
    with pytest.raises(ValueError, match="too short"):
        rollout_loss(shift_predictor(0.0), z, context=2, steps=4)
    with pytest.raises(ValueError, match="steps"):
        rollout_loss(shift_predictor(0.0), z, steps=0)
    with pytest.raises(ValueError, match="batch, time"):
        rollout_loss(shift_predictor(0.0), z[:, 0], steps=2)
    model = VideoJEPA(VIDEO_MODEL_CONFIGS["ci"])
    with pytest.raises(ValueError, match="windows"):
        model.predictor(torch.randn(2, 3, 8, 8, 8))
    short = torch.zeros(4, 5, 1, 64, 64, dtype=torch.uint8)
    with pytest.raises(ValueError, match="at least 6"):
        grid_features(model, short, horizons=4)
    with pytest.raises(ValueError, match="uint8"):
        grid_features(model, torch.zeros(4, 8, 1, 64, 64), horizons=4)


def test_grid_features_reads_in_eval_mode_and_hands_the_model_back_as_it_was():
    """Batch norm's running statistics, not the clips', give the features (a model scored in
    the middle of training then trains on in training mode)."""
    model = VideoJEPA(VIDEO_MODEL_CONFIGS["ci"]).train()
    clips = torch.randint(0, 256, (3, 8, 1, 64, 64), dtype=torch.uint8)
    encoded, _ = grid_features(model, clips, horizons=2)
    assert model.training
    with torch.no_grad():
        expected = torch.nn.functional.adaptive_avg_pool2d(
            model.eval().encode(clips).flatten(0, 1), 8)
    assert torch.allclose(encoded.flatten(0, 1), expected, atol=1e-6)
    assert not model.training  # (the eval() just above)
    grid_features(model, clips, horizons=2)
    assert not model.training


@pytest.mark.slow  # trains, resumes, probes and decodes: seconds
def test_training_resumes_and_evaluation_runs(digits, tmp_path):
    clips = generate_moving_mnist(digits, 32, 10, seed=1).clips
    config = replace(CI, steps=4, batch_size=4)
    model, history = train_video_jepa(config, clips)
    assert {"prediction", "variance", "covariance"} <= set(history)
    path = tmp_path / "video.pt"
    train_video_jepa(config, clips, checkpoint=path)
    again, _ = train_video_jepa(config, clips, checkpoint=path)  # restored, done
    for a, b in zip(model.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)

    probe_data = generate_moving_mnist(digits, 8, 10, seed=2)
    eval_data = generate_moving_mnist(digits, 8, 10, seed=3)
    for unroll in ("parallel", "autoregressive"):
        report = detection_report(model, probe_data, eval_data, horizons=7, probe_steps=3,
                                  unroll=unroll)
        for name in ("ap", "ap_encoded", "ap_copy"):
            assert report[name].shape == (7,) and ((report[name] >= 0) & (report[name] <= 1)).all()
        assert report["map"] == pytest.approx(float(report["ap"].mean()))
        # the baselines' frames, one frame at a time: horizon k scores each frame t from
        # context - 1 + k on against the true latent of t (encoded) and of t - k (copy)
        encoded, _ = grid_features(model, eval_data.clips, horizons=7, unroll=unroll)
        cells, context = centres_to_grid(eval_data.centres), model.config.context
        for k in range(1, 8):
            frames = range(context - 1 + k, cells.shape[1] if unroll == "parallel" else context + k)
            truth = torch.stack([cells[:, t] for t in frames], 1).flatten(0, 1)
            for name, shift in (("ap_encoded", 0), ("ap_copy", k)):
                latents = torch.stack([encoded[:, t - shift] for t in frames], 1).flatten(0, 1)
                with torch.no_grad():
                    scores = report["probe"](latents)
                assert report[name][k - 1] == pytest.approx(average_precision(scores, truth))
    cosine = tmp_path / "cosine.pt"  # the rate falls to 0 at the last step
    train_video_jepa(replace(config, recipe=replace(CI.recipe, cosine=True)), clips,
                     checkpoint=cosine)
    state = load_checkpoint(cosine)
    assert state["scheduler"]["last_epoch"] == config.steps
    assert state["optimizer"]["param_groups"][0]["lr"] == pytest.approx(0.0, abs=1e-12)
    decoder = NOTEBOOK.fit_decoder(model, clips, steps=2, batch_size=4)
    with torch.no_grad():
        z = model.encode(clips[:2])[:, 0]
        assert torch.sigmoid(decoder(z)).shape == (2, 1, 64, 64)


def test_the_papers_constant_rate_is_a_scheduler_that_keeps_it(digits, tmp_path):
    clips = generate_moving_mnist(digits, 8, 10, seed=1).clips
    # the paper's constant 1e-3 way
    config = replace(CI, steps=2, batch_size=2, recipe=replace(CI.recipe, cosine=False))
    path = tmp_path / "constant.pt"
    train_video_jepa(config, clips, checkpoint=path)
    state = load_checkpoint(path)  # the step calls scheduler.step() whatever the config
    assert state["scheduler"]["last_epoch"] == config.steps
    assert state["optimizer"]["param_groups"][0]["lr"] == config.lr


def test_the_curriculum_trains_one_step_first_then_k_steps(digits, monkeypatch):
    class_ = VIDEO_CONFIGS["class"]  # 2,400 steps, the first half at K = 1
    assert class_.switch_step == 1200 and class_.rollout_steps == 4
    assert replace(class_, recipe=PAPER_RECIPE).switch_step == 0
    seen = []  # K of every loss the training loop computes

    def recording(predictor, z, context, steps, detach_later):
        seen.append(steps)
        return parallel_rollout_loss(predictor, z, context, steps, detach_later)

    monkeypatch.setattr(video_training, "parallel_rollout_loss", recording)
    clips = generate_moving_mnist(digits, 8, 10, seed=1).clips
    config = replace(CI, steps=5, batch_size=2, rollout_steps=3,
                     recipe=replace(CI.recipe, one_step_fraction=0.4))
    train_video_jepa(config, clips)
    assert seen == [1, 1, 3, 3, 3]


def test_a_run_hands_its_one_step_half_to_the_same_run_with_another_k(digits, tmp_path):
    clips = generate_moving_mnist(digits, 8, 10, seed=1).clips
    one = replace(CI, steps=6, batch_size=2, rollout_steps=1)  # the first half at K = 1
    three = replace(one, rollout_steps=3)
    assert one.switch_step == 3 and train_video.shares_start_with(one, three)
    assert not train_video.shares_start_with(one, replace(three, seed=1))
    no_curriculum = replace(CI.recipe, one_step_fraction=0.0)
    assert not train_video.shares_start_with(replace(one, recipe=no_curriculum),
                                             replace(three, recipe=no_curriculum))
    scratch, scratch_history = train_video_jepa(three, clips)
    handed = tmp_path / "three.partial"
    train_video_jepa(one, clips,
                     after=train_video.handover(one, [(three, handed)]))
    assert load_checkpoint(handed)["step"] == 3
    resumed, history = train_video_jepa(three, clips, checkpoint=handed)
    assert history == scratch_history
    for a, b in zip(scratch.state_dict().values(), resumed.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="only to the same run with another K"):
        train_video.handover(one, [(replace(three, seed=1), handed)])


def test_after_sees_the_training_model_after_every_step(digits):
    clips = generate_moving_mnist(digits, 8, 10, seed=1).clips
    config = replace(CI, steps=3, batch_size=2)
    calls = []  # (steps done, a copy of one weight, train mode, rows logged) at each call

    def hook(done, parts, history):
        model = parts[0]
        calls.append((done, next(model.parameters()).detach().clone(), model.training,
                      len(history["step"])))

    model, _ = train_video_jepa(config, clips, after=hook)
    assert [done for done, *_ in calls] == [1, 2, 3] and all(c[2] for c in calls)
    assert [c[3] for c in calls] == [1, 1, 2]  # steps 0 and 2 (the last) are logged
    assert not torch.equal(calls[0][1], calls[1][1])  # each call sees the step just taken
    assert torch.equal(calls[-1][1], next(model.parameters()))  # the model returned


def test_train_or_load_trains_once_then_loads(digits, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))  # checkpoints go to tmp_path/checkpoints
    config = replace(CI, n_clips=16, steps=2, batch_size=2)
    model, history = train_or_load(config, "video_test", digits, device="cpu")
    assert "Trained and saved" in capsys.readouterr().out
    assert (tmp_path / "checkpoints" / "video_test.pt").is_file()
    assert not (tmp_path / "checkpoints" / "video_test.partial").exists()
    again, history_again = train_or_load(config, "video_test", digits)
    assert "Loaded a trained model" in capsys.readouterr().out
    assert history_again == history and not again.training
    for a, b in zip(model.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)
    # other training digits (or another config) must not reuse the saved run
    train_or_load(config, "video_test", 255 - digits)
    assert "another configuration" in capsys.readouterr().out


def test_run_names_and_ablation_configs():
    runs = ablation_configs(CI, rollout_steps=(1, 4), seeds=(0, 2))
    assert [(r.rollout_steps, r.seed) for r in runs] == [(1, 0), (1, 2), (4, 0), (4, 2)]
    assert all(replace(r, rollout_steps=CI.rollout_steps, seed=CI.seed) == CI for r in runs)
    assert run_name("ci", runs[1]) == "video_jepa_ci_K1_seed2"
    assert len({run_name("class", r) for r in runs}) == len(runs)


def test_an_unroll_other_than_the_default_is_another_run():
    k4, k1 = replace(CI, rollout_steps=4), replace(CI, rollout_steps=1)
    autoregressive = replace(k4, unroll="autoregressive")
    assert video_training.identity(autoregressive) != video_training.identity(k4)
    assert video_training.identity(autoregressive)["unroll"] == "autoregressive"
    assert "unroll" not in video_training.identity(k1)  # left at its default: not stored


def test_evaluation_clips_use_their_own_digits_and_seeds(digits):
    held_out = digits.clone()
    held_out[:, :, 9:19, 9:19] = 128  # grey squares: recognisably other digits
    probe_data, eval_data = evaluation_clips(digits, held_out, 4, 3)
    assert probe_data.clips.shape == (4, 10, 1, 64, 64) and eval_data.clips.shape[0] == 3
    assert set(probe_data.clips.unique().tolist()) == {0, 255}
    assert set(eval_data.clips.unique().tolist()) == {0, 128}
    again, _ = evaluation_clips(digits, held_out, 4, 3)
    assert torch.equal(again.clips, probe_data.clips)  # fixed seeds: the same for every model


def test_clips_given_as_the_whole_batch_are_told_to_pass_its_clips(digits):
    batch = generate_moving_mnist(digits, 2, 4, seed=0)
    check_clips(batch.clips, min_frames=4)
    with pytest.raises(ValueError, match=r"generate_moving_mnist's batch.clips; got "
                                         r"MovingMNISTBatch"):
        check_clips(batch, min_frames=4)


def test_moving_mnist_figures(digits):
    import matplotlib

    matplotlib.use("agg")
    batch = generate_moving_mnist(digits, 2, 5, seed=0)
    html = viz.play(viz.animate_clips(batch.clips, batch.centres, grid=8))
    assert "<script" in html.data and "font-awesome" not in html.data  # plays offline
    axes = viz.show_frame_rows({"real": (0, batch.clips[0]), "late": (2, batch.clips[1, :3])},
                               n_frames=5)
    assert axes.shape == (2, 5) and not axes[1, 1].axison and axes[1, 2].axison
    ax = viz.plot_ap_curves({"a": torch.tensor([0.5, 0.4])},
                            spread={"a": (torch.tensor([0.4, 0.3]), torch.tensor([0.6, 0.5]))})
    assert len(ax.get_lines()) == 1


def test_clip_animations_draw_each_frame_and_mark_the_centres_half_a_pixel_up_left(digits):
    """A frame of ``animate_clips`` shows that frame of every clip in grey levels 0..1, a
    cross on each digit's centre moved by -0.5 px (pixel i covers [i, i + 1); imshow puts its
    centre at i), and the grid's lines between pixels 7 | 8, 15 | 16, ..."""
    import matplotlib

    matplotlib.use("agg")
    batch = generate_moving_mnist(digits, 2, 4, seed=0)
    animation = viz.animate_clips(batch.clips, batch.centres, grid=8)
    animation._init_draw()  # its first frame, as a notebook's first draw would (else it warns)
    images, marks = (drawn := animation._func(3))[:2], drawn[2:]  # FuncAnimation's, at frame 3
    for i in range(2):
        assert torch.equal(torch.as_tensor(images[i].get_array()), batch.clips[i, 3, 0] / 255)
        assert marks[i].get_xydata().tolist() == (batch.centres[i, 3] - 0.5).tolist()
    grid_lines = images[0].axes.lines[1:]  # after the cross: a row's line, then a column's
    edges = [8 * k - 0.5 for k in range(1, 8)]
    assert [line.get_ydata()[0] for line in grid_lines[0::2]] == edges
    assert [line.get_xdata()[0] for line in grid_lines[1::2]] == edges
    matplotlib.pyplot.close(images[0].figure)


def test_frame_rows_put_each_frame_in_its_time_column(digits):
    """A row starting at ``first = 2`` shows its frame k in column 2 + k, in grey levels 0..1,
    the columns before it blank and unframed; the columns are titled by time step."""
    import matplotlib

    matplotlib.use("agg")
    frames = generate_moving_mnist(digits, 1, 2, seed=0).clips[0]  # uint8 (2, 1, 64, 64)
    axes = viz.show_frame_rows({"late": (2, frames)}, n_frames=4)
    for k in range(2):
        shown = torch.as_tensor(axes[0, 2 + k].images[0].get_array())
        assert torch.equal(shown, frames[k, 0] / 255)
    assert not axes[0, 0].images and not axes[0, 1].images and axes[0, 0].get_ylabel() == "late"
    assert not any(spine.get_visible() for spine in axes[0, 0].spines.values())
    assert [ax.get_title() for ax in axes[0]] == ["t=0", "t=1", "t=2", "t=3"]
    matplotlib.pyplot.close(axes[0, 0].figure)


def test_ap_curves_start_at_one_step_ahead_with_the_spread_as_a_band():
    """AP at horizons k = 1 .. H, and the band spans each label's (low, high), not the curve."""
    import matplotlib

    matplotlib.use("agg")
    ax = viz.plot_ap_curves({"a": torch.tensor([0.5, 0.4])},
                            spread={"a": (torch.tensor([0.4, 0.3]), torch.tensor([0.6, 0.5]))})
    ((horizons, ap),) = (line.get_data() for line in ax.get_lines())
    assert list(horizons) == [1, 2] and list(ap) == pytest.approx([0.5, 0.4])
    (band,) = ax.collections
    corners = {(round(x, 6), round(y, 6)) for x, y in band.get_paths()[0].vertices.tolist()}
    assert {(1, 0.4), (2, 0.3), (2, 0.5), (1, 0.6)} <= corners
    matplotlib.pyplot.close(ax.figure)


@pytest.mark.slow
def test_command_line_trains_and_reports(digits, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    stand_in = digits.repeat(20, 1, 1, 1)  # 160 "digits": the ci preset holds out all but 8000
    monkeypatch.setattr("research.train_video.load_mnist",
                        lambda split: (stand_in, torch.zeros(len(stand_in), dtype=torch.long)))
    monkeypatch.setattr("ebjepa_tutorial.course.presets.PRESETS", {"03": {"ci": replace(
        video_jepa_preset(), n_train_digits=120, n_probe=8, n_eval=8, probe_steps=5)}})
    monkeypatch.setattr("ebjepa_tutorial.training.checkpoints.SHIPPED_DIR", tmp_path / "ship")
    train_video.main(["--scale", "ci", "--K", "1", "--ship"])
    out = capsys.readouterr().out
    assert "video_jepa_ci_K1_seed0" in out and (tmp_path / "checkpoints").is_dir()
    for protocol in ("parallel", "autoregressive"):  # the paper's, then a planner's
        assert f"random init, {protocol} protocol: mAP" in out
        assert f"K=1 seed=0, {protocol} protocol: mAP" in out
    shipped = load_checkpoint(tmp_path / "ship" / "video_jepa_ci_K1_seed0.pt")
    assert {v.dtype for v in shipped["model"].values() if v.is_floating_point()} == {
        torch.float16}
    (tmp_path / "checkpoints" / "video_jepa_ci_K1_seed0.pt").unlink()  # the shipped copy loads
    train_video.main(["--scale", "ci", "--K", "1"])
    assert "Loaded a trained model from " + str(tmp_path / "ship") in capsys.readouterr().out
    seen = []  # K of every training loss: K = 4 trains only its steps after the switch

    def recording(predictor, z, context, steps, detach_later):
        seen.append(steps)
        return parallel_rollout_loss(predictor, z, context, steps, detach_later)

    monkeypatch.setattr(video_training, "parallel_rollout_loss", recording)
    train_video.main(["--scale", "ci", "--long"])  # the preset's long runs: K = 1 and 4
    out = capsys.readouterr().out
    assert "video_jepa_ci_long_K1_seed0" in out and "video_jepa_ci_long_K4_seed0" in out
    assert "K=4 seed=0, parallel protocol: mAP" in out
    assert seen == [1, 1, 1, 4]  # 3 steps each, switching after 2
    train_video.main(["--scale", "ci", "--K", "4", "--unroll", "autoregressive"])
    assert "video_jepa_ci_autoregressive_K4_seed0" in capsys.readouterr().out
    assert len(seen) == 4  # the autoregressive loss trained it


def video_jepa_preset():
    """The ci preset of notebook 03, with a shorter run for the command-line test."""
    from ebjepa_tutorial.course.presets import PRESETS

    ci = PRESETS["03"]["ci"]
    short = replace(ci.train, n_clips=16, steps=2, batch_size=2)
    return replace(ci, train=short, long_config=replace(short, steps=3))


class _PlusOne(torch.nn.Module):
    """A predictor "last latent + 1": a step k ahead of its newest true latent is that + k."""

    def forward(self, window):
        return window[:, -1] + 1


@pytest.mark.parametrize("unroll", ["autoregressive", "parallel"])
def test_each_horizon_scores_the_predictions_that_many_steps_ahead(unroll):
    from ebjepa_tutorial.evaluation.detection import _pool

    torch.manual_seed(0)
    digits = torch.zeros(8, 1, 28, 28, dtype=torch.uint8)
    digits[:, :, 9:19, 9:19] = 255
    model = VideoJEPA(VIDEO_MODEL_CONFIGS["ci"]).eval()
    model.predictor = _PlusOne()
    clips = generate_moving_mnist(digits, 3, 10, seed=3).clips  # (3, 10, 1, 64, 64)
    c = model.config.context
    with torch.no_grad():
        z = _pool(model.encode(clips))  # (3, 10, C, 8, 8)
    _, predicted = grid_features(model, clips, horizons=4, unroll=unroll)
    for k in range(1, 5):
        # one rollout from the first c frames: entry k - 1 is frame c - 1 + k; the parallel
        # unroll: every frame from c - 1 + k on, each k steps past its newest true latent
        expected = z[:, c - 1:c] + k if unroll == "autoregressive" else z[:, c - 1:10 - k] + k
        assert torch.allclose(predicted[k - 1], expected, atol=1e-5), k
