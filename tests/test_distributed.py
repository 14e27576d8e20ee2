"""Several processes through torchrun: the batch statistics, gradients and checkpoints of a
two-process run (gloo on this CPU) equal those of one process on the whole batch, for the
image chapters (01-02), the video JEPA (03) and the world model (05).

The multi-process tests start two processes with ``torch.multiprocessing`` (or torchrun)
and a process group on 127.0.0.1; every check runs inside both ranks, and a failed
assertion on either fails the test. The fast tests run two ranks as two threads with
stand-in collectives, so the arithmetic around the collectives is checked in the inner loop.
"""

import copy
import os
import re
import socket
import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from test_data import shared_data
from torch import nn

from ebjepa_tutorial import distributed
from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.data.mnist import find_mnist, load_mnist
from ebjepa_tutorial.data.moving_mnist import split_digits
from ebjepa_tutorial.envs import generate_trajectories
from ebjepa_tutorial.losses import covariance_term, variance_term, vicreg_loss
from ebjepa_tutorial.losses.rollout import parallel_rollout_loss
from ebjepa_tutorial.losses.sigreg import sigreg, sigreg_loss
from ebjepa_tutorial.losses.world import (
    WorldLossCoeffs,
    encode_for_loss,
    inverse_dynamics_loss,
    multistep_prediction_loss,
    temporal_similarity_loss,
    variance_covariance_loss,
)
from ebjepa_tutorial.models.video import VideoJEPA, VideoModelConfig
from ebjepa_tutorial.models.world import WorldConfig, WorldModel
from ebjepa_tutorial.training import image, video, world
from ebjepa_tutorial.training.checkpoints import load_checkpoint
from ebjepa_tutorial.training.loop import History, load_or_train
from ebjepa_tutorial.utils import at_least_float32, mixed_precision
from research import launch, train_image, train_video, train_world

REPO = Path(__file__).resolve().parents[1]
WORLD = 2
TINY = image.ImageJEPAConfig(widths=(4, 4, 8, 8), projector=(16, 16), batch_size=8, steps=4,
                             warmup_steps=1, image_size=16)
VIDEO_TINY = video.VideoJEPAConfig(
    model=VideoModelConfig(encoder_width=4, stem_stride=1, latent_channels=4, strides=(2, 2, 2),
                           predictor_width=4, predictor_levels=1, projector_dim=8),
    n_frames=4, rollout_steps=2, batch_size=4, recipe=video.Recipe(channels_last=False))
WORLD_TINY = WorldConfig(widths=(4, 8), blocks=1, input_size=17, latent_dim=8,
                         action_embed_dim=8, idm_hidden=16)
# every term on, SIGReg included, with still steps: each draws from the generator or reads
# the whole batch
WORLD_RUN = world.WorldTrainConfig(model=WORLD_TINY, coeffs=WorldLossCoeffs(sigreg=0.5),
                                   rollout_steps=3, recipe=world.Recipe(stay_probability=0.3))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def spawn(worker, *args) -> None:
    """Run ``worker(rank, *args)`` in WORLD processes joined by a gloo group on 127.0.0.1."""
    mp.spawn(_joined, args=(worker, free_port(), args), nprocs=WORLD, join=True)


def _joined(rank, worker, port, args):
    torch.set_num_threads(1)  # two processes share the cores
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank,
                            world_size=WORLD)
    try:
        worker(rank, *args)
    finally:
        dist.destroy_process_group()


def _images(n=32, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, 3, 32, 32), dtype=torch.uint8, generator=generator)


# --- one process: nothing changes ------------------------------------------------------------


def _loss_and_grads(loss_fn, across_ranks):
    z_a = torch.randn(16, 8, generator=torch.Generator().manual_seed(0), requires_grad=True)
    z_b = torch.randn(16, 8, generator=torch.Generator().manual_seed(1), requires_grad=True)
    total, terms = loss_fn(z_a, z_b, across=across_ranks)
    total.backward()
    return total, terms, z_a.grad, z_b.grad


def _global(across, *z):
    """The views as the loss sees them: every rank's rows gathered, as in training."""
    return tuple(map(distributed.gather_rows, z)) if across else z


LOSSES = {
    "vicreg": lambda z_a, z_b, across: vicreg_loss(*_global(across, z_a, z_b), 1.0, 2.0, 160.0),
    "sigreg": lambda z_a, z_b, across: sigreg_loss(
        *_global(across, z_a, z_b), num_slices=32, generator=torch.Generator().manual_seed(3)),
}


@pytest.mark.parametrize("loss", LOSSES)
def test_one_process_gives_the_same_bits_with_or_without_the_wrappers(loss):
    plain = _loss_and_grads(LOSSES[loss], across_ranks=False)
    across = _loss_and_grads(LOSSES[loss], across_ranks=True)
    assert plain[1] == across[1]
    assert all(torch.equal(p, q) for p, q in zip(plain[:1] + plain[2:], across[:1] + across[2:]))


def _video_case():
    """A video model and 4 clips of 4 frames in [0, 1]. Its batch norm is in eval mode (fixed
    statistics), so each clip's output depends on that clip alone, as the comparison of a
    split batch with the whole one needs (training normalises over each rank's frames)."""
    torch.manual_seed(0)
    return VideoJEPA(VIDEO_TINY.model).eval(), torch.rand(4, 4, 1, 64, 64)


def _video_whole(model, frames):
    """The video loss of one process on the whole batch, written out with the plain losses,
    and its gradient in ``.grad``: what the training step must reproduce on every rank."""
    with mixed_precision(frames.device, cpu=True):  # as training (float32 on most CPUs)
        z = model.encode(frames)
        prediction = parallel_rollout_loss(model.predictor, z, 2, VIDEO_TINY.rollout_steps,
                                           VIDEO_TINY.recipe.detach_later_orders)
        projected = model.project(z)
    projected = at_least_float32(projected)
    variance, covariance = variance_term(projected), covariance_term(projected)
    total = prediction + video.STD_COEFF * variance + video.COV_COEFF * covariance
    total.backward()
    terms = {"prediction": prediction, "variance": variance, "covariance": covariance}
    return total.detach(), {name: value.detach() for name, value in terms.items()}


def _video_step(model, frames):
    """The training step itself (``video_jepa_step``) on these rows, at a rate of 0: the
    weights stay, and the gradients it averaged over the ranks stay in ``.grad``."""
    optimizer = torch.optim.SGD(model.parameters(), lr=0.0)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda n: 1.0)
    return video.video_jepa_step(model, optimizer, scheduler, frames, VIDEO_TINY.rollout_steps,
                                 VIDEO_TINY)


def _world_case():
    """A world model (no batch norm) and 4 trajectories of 5 actions, in the default dtype."""
    trajectories = generate_trajectories(4, steps=5, seed=0)
    rendered = torch.empty(4, 6, 2, 65, 65, dtype=torch.float32)  # render draws in float32
    dtype = torch.get_default_dtype()
    frames = trajectories.frames(out=rendered).to(dtype)
    actions = trajectories.actions.to(dtype)
    torch.manual_seed(0)
    return WorldModel(WORLD_TINY).to(dtype).fit_input_stats(frames), frames, actions


def _world_whole(model, frames, actions):
    """The world model's loss of one process on the whole batch, written out with the plain
    terms (no collective), and its gradient in ``.grad``: what the step must reproduce."""
    generator = torch.Generator().manual_seed(5)  # the still steps', then SIGReg's draws
    coeffs, z = WORLD_RUN.coeffs, encode_for_loss(model, frames)
    terms = {"prediction": multistep_prediction_loss(
                 model.predict, z, actions, WORLD_RUN.rollout_steps,
                 stay_probability=WORLD_RUN.recipe.stay_probability, generator=generator),
             "temporal": temporal_similarity_loss(z),
             "inverse_dynamics": inverse_dynamics_loss(model.predict_actions, z, actions)}
    terms["variance"], terms["covariance"] = variance_covariance_loss(z)
    terms["sigreg"] = sigreg(z.reshape(-1, z.shape[-1]), generator=generator)
    total = sum(getattr(coeffs, name) * value for name, value in terms.items())
    total.backward()
    return total.detach(), {name: value.detach() for name, value in terms.items()}


def _world_step(model, frames, actions):
    """The training step itself (``world_model_step``) on these rows, at a rate of 0: the
    weights stay, and the gradients it averaged over the ranks stay in ``.grad``."""
    generator = torch.Generator().manual_seed(5)  # seeded alike on every rank, as in training
    optimizer = torch.optim.SGD(model.parameters(), lr=0.0)
    return world.world_model_step(model, optimizer, frames, actions, generator, WORLD_RUN, step=0)


# chapter -> (its model and inputs, the whole batch in one process, training's code on some rows)
CHAPTERS = {"video": (_video_case, _video_whole, _video_step),
            "world": (_world_case, _world_whole, _world_step)}


@pytest.mark.parametrize("chapter", CHAPTERS)
def test_one_process_chapter_steps_give_the_same_bits_as_the_plain_losses(chapter):
    make, *ways = CHAPTERS[chapter]
    runs = []
    for way in ways:
        model, *inputs = make()
        model.train()  # as in training: one process normalises over its whole batch
        total, terms = way(model, *inputs)
        runs.append((total, terms, [p.grad for p in model.parameters()]))
    (total, terms, grads), (again, terms_again, grads_again) = runs
    assert torch.equal(total, again) and terms == terms_again
    assert all(torch.equal(g, h) for g, h in zip(grads, grads_again, strict=True))


def test_helpers_are_no_ops_in_one_process():
    x = torch.randn(4, 3)
    assert (distributed.world_size(), distributed.is_main()) == (1, True)
    assert distributed.gather_rows(x) is x
    drawn = distributed.rand_rows(3, 2, generator=torch.Generator().manual_seed(1))
    assert torch.equal(drawn, torch.rand(3, 2, generator=torch.Generator().manual_seed(1)))
    assert distributed.local_rows(x) is x and distributed.mean_of_floats([1.5]) == [1.5]
    module = nn.Linear(2, 2)
    assert distributed.data_parallel(module, "cpu") is module
    assert distributed.from_main(lambda: 7) == 7
    module.weight.grad = torch.ones(2, 2)
    distributed.average_gradients(module.parameters())  # a bias without a gradient is skipped
    assert torch.equal(module.weight.grad, torch.ones(2, 2)) and module.bias.grad is None


def test_the_global_batch_must_split_evenly(monkeypatch):
    monkeypatch.setattr(distributed, "world_size", lambda: 4)
    assert distributed.per_rank_batch(256) == 64
    with pytest.raises(ValueError, match="30 cannot be split evenly over 4 processes"):
        distributed.per_rank_batch(30)
    with pytest.raises(ValueError, match="at least 2 samples each"):
        distributed.per_rank_batch(4)


def test_each_rank_takes_its_own_block_of_the_global_batch(monkeypatch):
    """Rank r of W holds rows r b .. (r+1) b of a global batch of W b rows: the shares, in rank
    order (as ``gather_rows`` joins them), give the global batch back, and each rank's part of
    a draw for the global batch (``rand_rows``) is that draw's rows of its block."""
    monkeypatch.setattr(distributed, "world_size", lambda: 2)
    batch = torch.arange(8)
    whole_draw = torch.rand(8, 3, generator=torch.Generator().manual_seed(1))
    shares, draws = [], []
    for rank in range(2):
        monkeypatch.setattr(dist, "get_rank", lambda rank=rank: rank)
        shares.append(distributed.local_rows(batch))
        draws.append(distributed.rand_rows(4, 3, generator=torch.Generator().manual_seed(1)))
    assert [share.tolist() for share in shares] == [[0, 1, 2, 3], [4, 5, 6, 7]]
    assert torch.equal(torch.cat(draws), whole_draw)


# --- two ranks in one process: the collectives' arithmetic, fast --------------------------------


class TwoThreads:
    """Two ranks as two threads of this process, with collectives that add or gather across
    them. Values only: autograd does not cross threads (the gloo tests check gradients)."""

    def __init__(self, monkeypatch):
        self.barrier, self.slots, self.local = threading.Barrier(WORLD), [None] * WORLD, \
            threading.local()
        for name, fake in [("get_world_size", lambda: WORLD), ("get_rank", self.rank),
                           ("get_backend", lambda: "gloo"), ("all_reduce", self.all_reduce),
                           ("broadcast_object_list", self.broadcast)]:
            monkeypatch.setattr(dist, name, fake)
        monkeypatch.setattr(distributed, "running", lambda: True)
        monkeypatch.setattr(distributed.collective, "all_reduce", self.summed)
        monkeypatch.setattr(distributed.collective, "all_gather", self.gathered)

    def rank(self) -> int:
        return self.local.rank

    def exchange(self, value) -> list:
        """Every rank's ``value``, in rank order."""
        self.slots[self.rank()] = value
        self.barrier.wait()
        everyone = list(self.slots)
        self.barrier.wait()  # no rank writes its next value before every rank has read these
        return everyone

    def all_reduce(self, tensor):  # in place, as torch.distributed's
        tensor.copy_(sum(self.exchange(tensor.clone())))

    def broadcast(self, box, src=0):
        box[:] = self.exchange(list(box))[src]

    def summed(self, tensor):  # autograd's all_reduce: this rank's tensor plus the others' values
        others = [t.detach() for r, t in enumerate(self.exchange(tensor)) if r != self.rank()]
        return tensor + sum(others)

    def gathered(self, tensor):
        return tuple(t if r == self.rank() else t.detach()
                     for r, t in enumerate(self.exchange(tensor)))

    def run(self, work) -> list:
        """``work(rank)`` on every rank at once: the results in rank order (an error re-raised)."""
        results, errors = [None] * WORLD, []

        def rank_main(rank):
            self.local.rank = rank
            try:
                results[rank] = work(rank)
            except BaseException as error:  # noqa: BLE001 - handed to the test's thread
                errors.append(error)
                self.barrier.abort()  # the other rank stops waiting

        threads = [threading.Thread(target=rank_main, args=(r,)) for r in range(WORLD)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=30)
        errors.sort(key=lambda error: isinstance(error, threading.BrokenBarrierError))
        if errors:  # the failure itself, not the other rank's broken wait
            raise errors[0]
        return results


def test_two_ranks_see_the_global_batch_s_variance_and_covariance(monkeypatch):
    z = torch.randn(8, 5, generator=torch.Generator().manual_seed(0)) * torch.arange(1.0, 6.0)
    ranks = TwoThreads(monkeypatch)
    results = ranks.run(lambda rank: distributed.variance_and_covariance(z[4 * rank:4 * rank + 4]))
    for variance, covariance in results:  # every rank: the terms of all 8 rows, not its 4
        assert torch.allclose(variance, variance_term(z), atol=1e-6)
        assert torch.allclose(covariance, covariance_term(z), atol=1e-6)
    gathered = ranks.run(lambda rank: distributed.gather_rows(z[4 * rank:4 * rank + 4]))
    assert all(torch.equal(rows, z) for rows in gathered)  # in rank order


def test_two_ranks_average_gradients_and_logged_numbers(monkeypatch):
    ranks = TwoThreads(monkeypatch)

    def work(rank):
        weight = nn.Parameter(torch.zeros(3))
        weight.grad = torch.tensor([1.0, 2.0, 3.0]) * (1 + 2 * rank)  # rank 0: g, rank 1: 3 g
        distributed.average_gradients([weight, nn.Parameter(torch.zeros(1))])  # no grad: skipped
        return weight.grad, distributed.mean_of_floats([1.0 + rank, 10.0 * rank])

    for grad, logged in ranks.run(work):
        assert grad.tolist() == [2.0, 4.0, 6.0] and logged == [1.5, 5.0]


def test_rank_0_s_result_or_error_reaches_every_rank(monkeypatch):
    ranks = TwoThreads(monkeypatch)
    assert ranks.run(lambda rank: distributed.from_main(lambda: {"rank": rank})) == [
        {"rank": 0}, {"rank": 0}]

    def failing(rank):
        try:
            distributed.from_main(lambda: int("not a number"))
        except ValueError:
            return "rank 0's own error"
        except RuntimeError as error:
            return str(error)

    assert ranks.run(failing) == [
        "rank 0's own error", "rank 0 failed: ValueError: invalid literal for int() with base 10: "
        "'not a number'"]


def test_init_names_the_missing_torchrun_variables():
    with pytest.raises(RuntimeError, match="MASTER_ADDR, MASTER_PORT are not set.*torchrun"):
        launch.init_from_env({"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0"})
    assert not distributed.running()


@pytest.fixture
def no_torchrun(monkeypatch):
    for name in launch.TORCHRUN_ENV:
        monkeypatch.delenv(name, raising=False)

    def no_data(split):
        raise AssertionError("the data was loaded before the set-up was checked")

    monkeypatch.setattr(train_image, "load_cifar10", no_data)


def test_a_distributed_flag_without_torchrun_is_a_clear_error(no_torchrun, capsys):
    with pytest.raises(SystemExit):
        train_image.main(["--scale", "ci", "--out", "x.pt", "--ddp"])
    assert "needs torchrun's environment, and RANK, WORLD_SIZE" in capsys.readouterr().err


@pytest.fixture
def no_torchrun_nor_work(no_torchrun, monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("the command started work before the set-up was checked")

    monkeypatch.setattr(train_video, "load_mnist", no_work)
    monkeypatch.setattr(train_world, "train_world_model", no_work)
    monkeypatch.setattr(train_world, "load_world_model", no_work)


@pytest.mark.parametrize("command, flags, message", [
    (train_video, ["--ddp"], "Start it with `torchrun --nproc_per_node=N -m "
                             "research.train_video ...`"),
    (train_world, ["--out", "x.pt", "--ddp"], "Start it with `torchrun --nproc_per_node=N -m "
                                              "research.train_world ...`"),
    (train_world, ["--refit", "m.pt", "--out", "x.pt", "--ddp"], "--refit runs in one process"),
], ids=["video --ddp", "world --ddp", "world --refit --ddp"])
def test_a_distributed_flag_without_torchrun_stops_the_video_and_world_commands(
        no_torchrun_nor_work, capsys, command, flags, message):
    with pytest.raises(SystemExit):
        command.main(["--scale", "ci", *flags] if command is train_video else flags)
    assert message in " ".join(capsys.readouterr().err.split())


def test_the_help_states_the_global_batch_rule(capsys):
    with pytest.raises(SystemExit):
        train_image.main(["--help"])
    words = " ".join(capsys.readouterr().out.split())
    assert "global batch = per-rank batch x world size" in words
    for documented in (distributed.per_rank_batch, train_video, train_world):
        assert "global batch = per-rank batch x" in " ".join(documented.__doc__.split())
    for command in (train_video, train_world):
        with pytest.raises(SystemExit):
            command.main(["--help"])
        assert "per-rank batch x world size" in " ".join(capsys.readouterr().out.split())


# --- two processes: the same numbers as one ------------------------------------------------


class Mlp(nn.Module):
    """A small network without batch norm, so its gradients on a split batch can equal the
    whole batch's (batch norm over each rank's share is another function)."""

    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(5, 32), nn.Tanh(), nn.Linear(32, 8))

    def forward(self, x):
        return self.net(x)


def _match_one_process(rank):
    for loss_name in LOSSES:
        _match_one_process_with(rank, loss_name)


def _match_one_process_with(rank, loss_name):
    torch.manual_seed(0)  # the same weights and data on both ranks
    torch.set_default_dtype(torch.float64)  # so that "equal" can mean 1e-12, not 1e-6
    model = Mlp()
    views = torch.randn(2, 16, 5)  # (views, global batch 16, 5 inputs)
    reference = copy.deepcopy(model)
    total, terms = LOSSES[loss_name](*image.AllViews(reference)(*views), across=False)
    total.backward()

    net = distributed.data_parallel(image.AllViews(model), "cpu")
    share = views[:, rank * 8:(rank + 1) * 8]  # (views, 8, 5): this rank's half of the batch
    local, local_terms = LOSSES[loss_name](*net(*share), across=True)
    local.backward()  # DDP averages the gradients over the ranks

    mean_total, *mean_terms = distributed.mean_of_floats(
        [float(local), *map(float, local_terms.values())])
    assert mean_total == pytest.approx(total.item(), rel=1e-12)
    for name, value in zip(local_terms, mean_terms):
        assert value == pytest.approx(float(terms[name]), rel=1e-12), (loss_name, name)
    for (name, p), q in zip(model.named_parameters(), reference.parameters()):
        assert torch.allclose(p.grad, q.grad, rtol=1e-10, atol=1e-14), (loss_name, name)


@pytest.mark.slow
def test_two_ranks_give_the_terms_and_gradients_of_one_process():  # VICReg and SIGReg
    spawn(_match_one_process)


def _chapters_match_one_process(rank):
    torch.set_default_dtype(torch.float64)  # so that "equal" can mean 1e-12, not 1e-6
    for chapter, (make, whole, training) in CHAPTERS.items():
        model, *inputs = make()  # the same weights and data on both ranks
        reference = copy.deepcopy(model)
        total, terms = whole(reference, *inputs)  # one process, the whole batch
        # training's code on this rank's half; it averages the gradients over the ranks
        local, local_terms = training(model, *map(distributed.local_rows, inputs))

        mean_total, *mean_terms = distributed.mean_of_floats(
            [float(local), *map(float, local_terms.values())])
        assert mean_total == pytest.approx(total.item(), rel=1e-12), chapter
        assert local_terms.keys() == terms.keys()
        for name, value in zip(local_terms, mean_terms):
            assert value == pytest.approx(float(terms[name]), rel=1e-12), (chapter, name)
        for (name, p), q in zip(model.named_parameters(), reference.parameters(), strict=True):
            assert torch.allclose(p.grad, q.grad, rtol=1e-10, atol=1e-14), (chapter, name)


@pytest.mark.slow
def test_two_ranks_give_the_video_and_world_terms_and_gradients_of_one_process():
    spawn(_chapters_match_one_process)


def _refuse_bad_setups(rank):
    launch.check_same_on_all_ranks({"lr": 0.1, "steps": 4})  # agreeing ranks pass
    with pytest.raises(RuntimeError, match="different configs"):
        launch.check_same_on_all_ranks({"lr": 0.1, "steps": 4 + rank})
    with pytest.raises(ValueError, match="multiple of the world size 2"):
        image.train_image_jepa(replace(TINY, batch_size=9), _images(), progress=False)
    with pytest.raises(ValueError, match="multiple of the world size 2"):
        train_video.notebook().train_video_jepa(
            replace(VIDEO_TINY, batch_size=9), torch.zeros(4, 4, 1, 64, 64, dtype=torch.uint8),
            video.video_jepa_step)
    with pytest.raises(ValueError, match="multiple of the world size 2"):  # before any data
        train_world.notebook().train_world_model(world.WorldTrainConfig(batch_size=9), None,
                                                 world.world_model_step, progress=False)

    def fails_on_rank_0():
        raise OSError("disk gone")

    with pytest.raises((OSError, RuntimeError), match="disk gone"):  # every rank, no hang
        distributed.from_main(fails_on_rank_0)
    dist.barrier()  # still in step after all of that


@pytest.mark.slow
def test_bad_setups_fail_on_every_rank_rather_than_hang():
    spawn(_refuse_bad_setups)


def _train_until_step_2(rank, checkpoint):
    calls, real_two_views = [], image.augment.two_views

    def dying_two_views(*args, **kwargs):  # both ranks stop while making step 2's views
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real_two_views(*args, **kwargs)

    image.augment.two_views = dying_two_views
    image.CHECKPOINT_EVERY = 1  # (this process's copy of the module)
    with pytest.raises(KeyboardInterrupt):
        image.train_image_jepa(replace(TINY, loss=image.SIGReg(slices=8)), _images(),
                               checkpoint=checkpoint, progress=False)


@pytest.mark.slow
def test_a_two_rank_checkpoint_resumes_in_one_process(tmp_path, monkeypatch):
    checkpoint = tmp_path / "run.pt"
    spawn(_train_until_step_2, checkpoint)
    assert [p.name for p in tmp_path.iterdir()] == ["run.pt"]  # rank 0's file, no temp left
    stored = load_checkpoint(checkpoint)
    assert stored["step"] == 2 and stored["history"]["step"] == [0]  # logged every 10 steps
    config = replace(TINY, loss=image.SIGReg(slices=8))
    batches, real_two_views = [], image.augment.two_views
    monkeypatch.setattr(image.augment, "two_views",
                        lambda *args: batches.append(1) or real_two_views(*args))
    _, history = image.train_image_jepa(config, _images(), checkpoint=checkpoint, progress=False)
    assert len(batches) == 2 and history["step"] == [0, 3]  # steps 2 and 3 ran in this process
    assert history["loss"][0] == stored["history"]["loss"][0]  # the two-rank part, kept


def _train_then_load(rank, path):
    torch.manual_seed(rank)  # different weights on each rank until one is loaded
    model = nn.Linear(2, 2)
    _, trained = load_or_train(path, model, lambda _: (model, History(loss=[float(rank)])),
                               {"steps": 1})
    assert trained["loss"] == [float(rank)]  # every rank trained; rank 0 saved its model
    again = nn.Linear(2, 2)
    _, loaded = load_or_train(path, again, lambda _: 1 / 0, {"steps": 1})  # read on rank 0, sent
    assert loaded["loss"] == [0.0]
    weights = [torch.empty_like(again.weight) for _ in range(WORLD)]
    dist.all_gather(weights, again.weight.detach())
    assert torch.equal(weights[0], weights[1])


@pytest.mark.slow
def test_load_or_train_saves_on_rank_0_and_loads_on_every_rank(tmp_path):
    spawn(_train_then_load, tmp_path / "run.pt")
    assert [p.name for p in tmp_path.iterdir()] == ["run.pt"]


# --- the commands under torchrun -------------------------------------------------------------


def torchrun(command: str, *args: str, processes: int = 2,
             **env: str) -> subprocess.CompletedProcess:
    """``python -m research.<command> args`` on ``processes`` processes under torchrun (1: a
    plain ``python -m``), each on one thread."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE", **env}
    launcher = [str(Path(sys.executable).with_name("torchrun")), "--nnodes=1",
                f"--nproc_per_node={processes}", "--master_addr=127.0.0.1",
                f"--master_port={free_port()}"]
    line = [*(launcher if processes > 1 else [sys.executable]), "-m", f"research.{command}",
            *args]
    return subprocess.run(line, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.slow  # two processes; the first run also decodes CIFAR-10 into the cache (~20 s)
def test_torchrun_trains_the_image_command_on_two_processes(tmp_path):
    out = tmp_path / "encoder.pt"
    done = torchrun("train_image", "--scale", "ci", "--steps", "4", "--out", str(out),
                    EBJEPA_DATA=str(shared_data()))
    assert done.returncode == 0, done.stderr[-3000:]
    assert "on 2 process(es)" in done.stdout and done.stdout.count("saved") == 1
    stored = load_checkpoint(out)
    config = replace(preset("01", "ci").config, steps=4)
    assert stored["config"] == image.identity(config, encoder_only=True)
    assert stored["processes"] == 2 and stored["history"]["step"] == [0, 3]  # logged: 0, last
    encoder = image.ImageJEPA(config).encoder
    encoder.load_state_dict({k: v.float() for k, v in stored["model"].items()})
    assert not out.with_suffix(".partial").exists()


def mnist_data() -> Path:
    """The folder of the MNIST test digits, which the video command makes its clips from."""
    return shared_data(lambda folder: find_mnist(folder, "test") is not None,
                       "the MNIST test digits (t10k-images-idx3-ubyte.gz and its labels)")


@pytest.mark.slow  # two processes train 20 steps, then rank 0 fits and scores two probes
def test_torchrun_trains_the_video_command_on_two_processes(tmp_path, monkeypatch):
    data = mnist_data()
    done = torchrun("train_video", "--scale", "ci", "--K", "1", EBJEPA_DATA=str(data),
                    EBJEPA_CACHE=str(tmp_path))  # checkpoints go to tmp_path/checkpoints
    assert done.returncode == 0, done.stderr[-3000:]
    assert "video_jepa_ci_K1_seed0: ready in" in done.stdout and "on 2 process(es)" in done.stdout
    assert done.stdout.count("Trained and saved") == 1
    assert "K=1 seed=0, parallel protocol: mAP" in done.stdout
    sizes = preset("03", "ci")
    config = replace(sizes.train, rollout_steps=1)
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))  # the digits as the command decoded them
    train_digits = split_digits(load_mnist("test", root=data)[0], n_train=sizes.n_train_digits)[0]
    stored = load_checkpoint(tmp_path / "checkpoints" / "video_jepa_ci_K1_seed0.pt")
    assert stored["config"] == video.identity(config, train_digits)
    assert stored["history"]["step"] == [0, 10, 19]  # logged every 10 steps and the last
    VideoJEPA(config.model).load_state_dict(stored["model"])
    assert not list((tmp_path / "checkpoints").glob("*.partial"))


@pytest.mark.slow  # 4 steps on two processes (rank 0 scores the probe), then on one
@pytest.mark.parametrize("flags, changes", [
    ([], {}),
    (["--window", "9", "--wall-fraction", "0.25", "--channels-last", "--replay-steps", "2",
      "--stay-probability", "0.15"],  # each rank renders its rows of the global windows, and
     {"window": 9, "wall_fraction": 0.25, "channels_last": True,  # replays the global buffer
      "replay_steps": 2, "stay_probability": 0.15}),
])
def test_torchrun_trains_the_world_command_on_two_processes(tmp_path, flags, changes):
    out = tmp_path / "world.pt"
    done = torchrun("train_world", "--scale", "ci", "--steps", "4", "--out", str(out), *flags)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "on 2 process(es)" in done.stdout and done.stdout.count("saved") == 1
    stored = load_checkpoint(out)
    ci = preset("05", "ci").train
    config = replace(ci, steps=4, recipe=replace(ci.recipe, **changes))
    assert stored["config"] == world.identity(config) and stored["processes"] == 2
    assert stored["history"]["step"] == [0, 3]  # logged every 10 steps and the last
    assert world.load_world_model(out).config == config.model
    assert not out.with_suffix(".partial").exists()
    # the same command on one process: the same run, up to the order of float sums
    alone = torchrun("train_world", "--scale", "ci", "--steps", "4", "--out",
                     str(tmp_path / "one.pt"), *flags, processes=1)
    assert alone.returncode == 0, alone.stderr[-3000:]
    one = load_checkpoint(tmp_path / "one.pt")
    assert one["config"] == stored["config"] and one["processes"] == 1
    for name, values in one["history"].items():
        assert stored["history"][name] == pytest.approx(values, rel=1e-5), name
    probe = re.compile(r"probe error [\d.]+ px")  # scored on rank 0 alone, as on one process
    assert probe.findall(done.stdout) == probe.findall(alone.stdout) != []


def _replays_agree(rank):
    world.REPLAY_BATCH, world.REPLAY_CAPACITY = 8, 16  # small, and shared 4 + 4 by the ranks
    torch.manual_seed(0)  # the same weights on both ranks
    model = WorldModel(WORLD_TINY)
    config = world.WorldTrainConfig(model=WORLD_TINY, batch_size=8, rollout_steps=2,
                                    recipe=world.Recipe(replay_steps=2))
    replay = world.LatentReplay(model, config, frames=3, device="cpu")
    mine = torch.Generator().manual_seed(rank)  # each rank adds windows of its own
    replay.add(torch.randn(4, 3, model.latent_dim, generator=mine),
               torch.randn(4, 2, WORLD_TINY.action_dim, generator=mine))
    replay(0)
    for name, p in model.named_parameters():  # the ranks' copies of each replayed weight
        copies = [torch.empty_like(p) for _ in range(WORLD)]
        dist.all_gather(copies, p.detach())
        assert torch.equal(copies[0], copies[1]), name


@pytest.mark.slow
def test_replay_updates_keep_the_ranks_weights_identical():
    # each rank replays its share of the draw, so without averaging the replay's gradients
    # the two copies of the predictor would drift apart with no error
    spawn(_replays_agree)
