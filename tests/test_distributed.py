"""Several processes through torchrun: the batch statistics, gradients and checkpoints of a
two-process run (gloo on this CPU) equal those of one process on the whole batch.

The multi-process tests start two processes with ``torch.multiprocessing`` (or torchrun)
and a process group on 127.0.0.1; every check runs inside both ranks, and a failed
assertion on either fails the test.
"""

import copy
import os
import socket
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import nn

from ebjepa_tutorial import distributed
from ebjepa_tutorial.commands import train_image
from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.losses import vicreg_loss
from ebjepa_tutorial.losses.sigreg import sigreg_loss
from ebjepa_tutorial.training import image
from ebjepa_tutorial.training.checkpoints import load_checkpoint

REPO = Path(__file__).resolve().parents[1]
WORLD = 2
TINY = image.ImageJEPAConfig(widths=(4, 4, 8, 8), projector=(16, 16), batch_size=8, steps=4,
                             warmup_steps=1, image_size=16)


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
    total, terms = loss_fn(z_a, z_b, across_ranks)
    total.backward()
    return total, terms, z_a.grad, z_b.grad


LOSSES = {
    "vicreg": lambda z_a, z_b, across: vicreg_loss(z_a, z_b, 1.0, 2.0, 160.0, across_ranks=across),
    "sigreg": lambda z_a, z_b, across: sigreg_loss(
        z_a, z_b, num_slices=32, generator=torch.Generator().manual_seed(3), across_ranks=across),
}


@pytest.mark.parametrize("loss", LOSSES)
def test_one_process_gives_the_same_bits_with_or_without_across_ranks(loss):
    plain = _loss_and_grads(LOSSES[loss], across_ranks=False)
    across = _loss_and_grads(LOSSES[loss], across_ranks=True)
    assert plain[1] == across[1]
    assert all(torch.equal(p, q) for p, q in zip(plain[:1] + plain[2:], across[:1] + across[2:]))


def test_helpers_are_no_ops_in_one_process():
    x, y = torch.randn(4, 3), torch.randn(5)
    assert (distributed.world_size(), distributed.rank(), distributed.is_main()) == (1, 0, True)
    assert distributed.gather_rows(x)[0] is x and distributed.mean_across_ranks(x, y)[1] is y
    assert distributed.local_rows(x) is x and distributed.mean_of_floats([1.5]) == [1.5]
    module = nn.Linear(2, 2)
    assert distributed.data_parallel(module, "cpu") is module
    assert distributed.from_main(lambda: 7) == 7


def test_the_global_batch_must_split_evenly():
    assert distributed.per_rank_batch(256, world=4) == 64
    with pytest.raises(ValueError, match="30 cannot be split evenly over 4 processes"):
        distributed.per_rank_batch(30, world=4)
    with pytest.raises(ValueError, match="fewer than 2 samples"):
        distributed.per_rank_batch(4, world=4)


def test_init_names_the_missing_torchrun_variables():
    with pytest.raises(RuntimeError, match="MASTER_ADDR, MASTER_PORT are not set.*torchrun"):
        distributed.init_from_env({"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0"})
    assert not distributed.running()


@pytest.fixture
def no_torchrun(monkeypatch):
    for name in distributed.TORCHRUN_ENV:
        monkeypatch.delenv(name, raising=False)

    def no_data(split):
        raise AssertionError("the data was loaded before the set-up was checked")

    monkeypatch.setattr(train_image, "load_cifar10", no_data)


@pytest.mark.parametrize("flags, message", [
    (["--ddp"], "needs torchrun's environment, and RANK, WORLD_SIZE"),
    (["--sync-bn"], "--sync-bn needs several processes")])
def test_a_distributed_flag_without_torchrun_is_a_clear_error(no_torchrun, capsys, flags, message):
    with pytest.raises(SystemExit):
        train_image.main(["--scale", "ci", "--out", "x.pt", *flags])
    assert message in capsys.readouterr().err


def test_the_help_states_the_global_batch_rule(capsys):
    with pytest.raises(SystemExit):
        train_image.main(["--help"])
    words = " ".join(capsys.readouterr().out.split())
    assert "global batch = per-rank batch x world size" in words and "SyncBatchNorm" in words
    assert "global batch = per-rank batch x world size" in " ".join(
        image.train_image_jepa.__doc__.split())


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
    views = torch.randn(2, 16, 5)  # (2 views, global batch 16, 5 inputs)
    reference = copy.deepcopy(model)
    total, terms = LOSSES[loss_name](*image.BothViews(reference)(*views), False)
    total.backward()

    net = distributed.data_parallel(image.BothViews(model), "cpu")
    share = views[:, rank * 8:(rank + 1) * 8]  # (2, 8, 5): this rank's half of the batch
    local, local_terms = LOSSES[loss_name](*net(*share), True)
    local.backward()  # DDP averages the gradients over the ranks

    mean_total, *mean_terms = distributed.mean_of_floats([local.item(), *local_terms.values()])
    assert mean_total == pytest.approx(total.item(), rel=1e-12)
    for name, value in zip(local_terms, mean_terms):
        assert value == pytest.approx(terms[name], rel=1e-12), (loss_name, name)
    for (name, p), q in zip(model.named_parameters(), reference.parameters()):
        assert torch.allclose(p.grad, q.grad, rtol=1e-10, atol=1e-14), (loss_name, name)


@pytest.mark.slow
def test_two_ranks_give_the_terms_and_gradients_of_one_process():  # VICReg and SIGReg
    spawn(_match_one_process)


def _refuse_bad_setups(rank):
    distributed.check_same_on_all_ranks({"lr": 0.1, "steps": 4})  # agreeing ranks pass
    with pytest.raises(RuntimeError, match="different configs"):
        distributed.check_same_on_all_ranks({"lr": 0.1, "steps": 4 + rank})
    with pytest.raises(ValueError, match="multiple of the world size 2"):
        image.train_image_jepa(replace(TINY, batch_size=9), _images(), progress=False)
    with pytest.raises(ValueError, match="CUDA devices only"):
        distributed.data_parallel(nn.BatchNorm1d(3), "cpu", sync_batchnorm=True)

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
    with pytest.raises(KeyboardInterrupt):
        image.train_image_jepa(replace(TINY, loss="sigreg", sigreg_slices=8), _images(),
                               checkpoint=checkpoint, checkpoint_every=1, progress=False)


@pytest.mark.slow
def test_a_two_rank_checkpoint_resumes_in_one_process(tmp_path, monkeypatch):
    checkpoint = tmp_path / "run.pt"
    spawn(_train_until_step_2, checkpoint)
    assert [p.name for p in tmp_path.iterdir()] == ["run.pt"]  # rank 0's file, no temp left
    stored = load_checkpoint(checkpoint)
    assert stored["step"] == 2 and stored["history"]["step"] == [0]  # logged every 10 steps
    config = replace(TINY, loss="sigreg", sigreg_slices=8)
    batches, real_two_views = [], image.augment.two_views
    monkeypatch.setattr(image.augment, "two_views",
                        lambda *args: batches.append(1) or real_two_views(*args))
    _, history = image.train_image_jepa(config, _images(), checkpoint=checkpoint, progress=False)
    assert len(batches) == 2 and history["step"] == [0, 3]  # steps 2 and 3 ran in this process
    assert history["loss"][0] == stored["history"]["loss"][0]  # the two-rank part, kept


# --- the command under torchrun --------------------------------------------------------------


def shared_data() -> Path:
    for candidate in (os.environ.get("EBJEPA_DATA"), REPO.parent / "shared" / "data"):
        if candidate and (Path(candidate) / "cifar10-jpeg.tar.gz").is_file():
            return Path(candidate)
    pytest.skip("CIFAR-10 is not on this machine (set EBJEPA_DATA to a folder holding "
                "cifar10-jpeg.tar.gz): the command trains on the real images")


@pytest.mark.slow  # two processes; the first run also decodes CIFAR-10 into the cache (~20 s)
def test_torchrun_trains_the_image_command_on_two_processes(tmp_path):
    env = {**os.environ, "EBJEPA_DATA": str(shared_data()), "OMP_NUM_THREADS": "1",
           "OMP_WAIT_POLICY": "PASSIVE"}
    out = tmp_path / "encoder.pt"
    torchrun = Path(sys.executable).with_name("torchrun")
    command = [str(torchrun), "--nnodes=1", "--nproc_per_node=2", "--master_addr=127.0.0.1",
               f"--master_port={free_port()}", "-m", "ebjepa_tutorial.commands.train_image",
               "--scale", "ci", "--steps", "4", "--out", str(out)]
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "on 2 process(es)" in done.stdout and done.stdout.count("saved") == 1
    stored = load_checkpoint(out)
    config = replace(preset("01", "ci").config, steps=4)
    assert stored["config"] == image.identity(config, encoder_only=True)
    assert stored["processes"] == 2 and stored["history"]["step"] == [0, 3]  # logged: 0, last
    encoder = image.ImageJEPA(config).encoder
    encoder.load_state_dict({k: v.float() for k, v in stored["model"].items()})
    assert not out.with_suffix(".partial").exists()
