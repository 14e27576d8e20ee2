"""The image-JEPA recipe: config checks, loss choice, reproducible and resumable training."""

import pytest
import torch

from ebjepa_tutorial import image_jepa
from ebjepa_tutorial.image_jepa import ImageJEPAConfig

TINY = ImageJEPAConfig(widths=(4, 4, 8, 8), projector=(16, 16), batch_size=8, steps=4,
                       warmup_steps=1, image_size=16)


def _images(n=32, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, 3, 32, 32), dtype=torch.uint8, generator=generator)


def test_unknown_names_are_rejected():
    with pytest.raises(ValueError, match="unknown loss 'simclr'"):
        ImageJEPAConfig(loss="simclr")
    with pytest.raises(ValueError, match="unknown optimizer"):
        ImageJEPAConfig(optimizer="sgd")


@pytest.mark.parametrize("loss, terms", [
    ("vicreg", {"invariance", "variance", "covariance"}),
    ("sigreg", {"invariance", "sigreg"}),
    ("invariance", {"invariance"}),
])
def test_each_loss_logs_its_terms(loss, terms):
    config = ImageJEPAConfig(loss=loss, sigreg_slices=8)
    z_a, z_b = torch.randn(16, 8), torch.randn(16, 8)
    total, logged = image_jepa.jepa_loss(config, z_a, z_b, torch.Generator().manual_seed(0))
    assert set(logged) == terms and torch.isfinite(total)


def test_model_shapes_with_and_without_projector():
    model = image_jepa.ImageJEPA(TINY)
    assert model(torch.randn(2, 3, 16, 16)).shape == (2, 16)
    bare = image_jepa.ImageJEPA(ImageJEPAConfig(widths=(4, 4, 8, 8), projector=None))
    assert bare(torch.randn(2, 3, 16, 16)).shape == (2, 8)


def test_training_is_reproducible_and_resumable(tmp_path, monkeypatch):
    images = _images()
    straight, history = image_jepa.train_image_jepa(TINY, images, progress=False)
    again, _ = image_jepa.train_image_jepa(TINY, images, progress=False)
    assert all(torch.equal(p, q) for p, q in zip(straight.parameters(), again.parameters()))

    # A kernel that dies while making the views of step 2 ...
    calls, real_two_views = [], image_jepa.augment.two_views

    def dying_two_views(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real_two_views(*args, **kwargs)

    ckpt = tmp_path / "run.pt"
    monkeypatch.setattr(image_jepa.augment, "two_views", dying_two_views)
    with pytest.raises(KeyboardInterrupt):
        image_jepa.train_image_jepa(TINY, images, checkpoint=ckpt, checkpoint_every=1,
                                    progress=False)
    monkeypatch.undo()
    # ... then a new run picks up at step 2 and ends where the uninterrupted run ended.
    resumed, history2 = image_jepa.train_image_jepa(TINY, images, checkpoint=ckpt,
                                                    progress=False)
    assert history2["step"] == history["step"]
    assert history2["loss"] == pytest.approx(history["loss"], rel=1e-5)
    for p, q in zip(straight.parameters(), resumed.parameters()):
        assert torch.allclose(p, q, atol=1e-6)


def test_probe_encoder_reports_both_accuracies():
    images, labels = _images(40), torch.arange(40) % 4
    model = image_jepa.ImageJEPA(TINY)
    result = image_jepa.probe_encoder(model.encoder, TINY, (images, labels), (images, labels))
    assert set(result) == {"probe_acc", "knn_acc"}
    assert 0.0 <= result["probe_acc"] <= 1.0


def test_train_or_load_trains_once_then_loads(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    images = _images()
    first, history = image_jepa.train_or_load(TINY, "tiny_run", images)
    assert "Trained and saved" in capsys.readouterr().out
    assert not (tmp_path / "checkpoints" / "tiny_run.partial").exists()
    again, history2 = image_jepa.train_or_load(TINY, "tiny_run", images)
    assert "Loaded" in capsys.readouterr().out
    assert history2 == history and not again.training
    assert all(torch.equal(p, q) for p, q in zip(first.parameters(), again.parameters()))
