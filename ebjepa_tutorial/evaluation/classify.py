"""Linear-probe and k-nearest-neighbour accuracy of frozen image features (chapters 01-02)."""

import hashlib
import json
import math

import torch
import torch.nn.functional as F
from torch import nn

from ..data.paths import atomic_file, cache_dir
from ..training.image import ImageJEPAConfig, resize
from ..utils import evaluating

KNN_K, KNN_TEMPERATURE = 20, 0.07  # the kNN's neighbours and the softness of their votes


def accuracy(logits: torch.Tensor, labels: torch.Tensor) -> float:
    """Fraction of rows of ``logits (N, C)`` whose arg-max is the label ``(N,)``."""
    return (logits.argmax(dim=1) == labels).float().mean().item()


class LinearProbe(nn.Module):
    """``head((x - mean) / std)``: features ``(N, D)`` standardised by stored train statistics."""

    def __init__(self, mean: torch.Tensor, std: torch.Tensor, head: nn.Linear):
        super().__init__()
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)
        self.head = head

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.head((features - self.mean) / self.std)


def linear_probe(train_features: torch.Tensor, train_labels: torch.Tensor,
                 test_features: torch.Tensor, test_labels: torch.Tensor):
    """``(test accuracy, LinearProbe)``: ``nn.Linear(D, C)`` on train-standardised features
    ``(N, D)``, labels ``(N,)``; seeded Adam at 1e-3 (cosine, decay 1e-4), batch 512, 30 epochs."""
    mean, std = train_features.mean(dim=0), train_features.std(dim=0) + 1e-6
    x_train = (train_features - mean) / std
    num_classes = int(max(train_labels.max(), test_labels.max())) + 1
    generator, epochs, batch_size = torch.Generator().manual_seed(0), 30, 512
    head = nn.Linear(x_train.shape[1], num_classes).to(x_train.device)
    with torch.no_grad():  # seeded initialisation, independent of the global RNG
        head.weight.copy_(torch.randn(head.weight.shape, generator=generator) * 0.01)
        head.bias.zero_()
    optimizer = torch.optim.Adam(head.parameters(), lr=1e-3, weight_decay=1e-4)
    steps = epochs * math.ceil(len(x_train) / batch_size)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps)
    for _ in range(epochs):
        order = torch.randperm(len(x_train), generator=generator)
        for rows in order.split(batch_size):
            loss = F.cross_entropy(head(x_train[rows]), train_labels[rows])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            scheduler.step()
    probe = LinearProbe(mean, std, head)
    with torch.no_grad():
        return accuracy(probe(test_features), test_labels), probe


@torch.no_grad()
def knn_predict(train_features: torch.Tensor, train_labels: torch.Tensor,
                query_features: torch.Tensor) -> torch.Tensor:
    """Labels ``(Q,)`` of queries ``(Q, D)``: the ``KNN_K`` nearest train rows (cosine) vote with
    weights ``exp(similarity / KNN_TEMPERATURE)``, the kNN of Wu et al. 2018 and DINO."""
    k = min(KNN_K, len(train_features))
    num_classes = int(train_labels.max()) + 1
    train = F.normalize(train_features.float(), dim=1)
    predictions = []
    for start in range(0, len(query_features), 512):
        query = F.normalize(query_features[start : start + 512].float(), dim=1)
        similarity, index = (query @ train.T).topk(k, dim=1)  # (q, k)
        votes = torch.zeros(len(query), num_classes, device=query.device)
        votes.scatter_add_(1, train_labels[index], (similarity / KNN_TEMPERATURE).exp())
        predictions.append(votes.argmax(dim=1))
    return torch.cat(predictions)


@torch.no_grad()
def embed(encoder: nn.Module, images: torch.Tensor, size: int):
    """Frozen features ``(N, D)`` float32 on the CPU of uint8 images ``(N, 3, 32, 32)``,
    normalised and resized to ``size`` px (32: not resized), the encoder in eval mode."""
    if images.dtype != torch.uint8:
        raise TypeError(f"embed expects the stored uint8 images, got {images.dtype}")
    device = next(encoder.parameters()).device
    with evaluating(encoder):
        chunks = [encoder(resize(images[i:i + 256].to(device), size)).float().cpu()
                  for i in range(0, len(images), 256)]
    return torch.cat(chunks)


def probe_encoder(encoder, config: ImageJEPAConfig, train, test, cache: bool = False) -> dict:
    """``{"probe_acc", "knn_acc"}`` on ``test`` of frozen features at ``config.eval_image_size``
    px; ``train``, ``test``: (images, labels). ``cache``: keep the scores in data/cache/probes/
    under a digest of the weights, protocol and data (not of this code)."""
    path = None
    if cache:  # the file's name: a digest of the weights, the protocol and the data
        protocol = f"probe and kNN (k = {KNN_K}) at {config.eval_image_size} px"
        digest = hashlib.sha1(protocol.encode())
        data = zip(("train", "train labels", "test", "test labels"), (*train, *test))
        for name, tensor in [*encoder.state_dict().items(), *data]:
            tensor = tensor.detach().cpu().contiguous()
            digest.update(f"{name} {tensor.dtype} {tuple(tensor.shape)}".encode())
            digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
        path = cache_dir() / "probes" / f"{digest.hexdigest()[:16]}.json"
        if path.exists():
            return json.loads(path.read_text())
    train_features = embed(encoder, train[0], config.eval_image_size)
    test_features = embed(encoder, test[0], config.eval_image_size)
    probe_acc, _ = linear_probe(train_features, train[1], test_features, test[1])
    knn = knn_predict(train_features, train[1], test_features) == test[1]
    scores = {"probe_acc": probe_acc, "knn_acc": knn.float().mean().item()}
    if path is not None:
        with atomic_file(path) as f:  # a killed write leaves no half file under the real name
            f.write(json.dumps(scores).encode())
    return scores

