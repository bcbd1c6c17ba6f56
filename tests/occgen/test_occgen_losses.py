import torch

from occgen.losses import kl_divergence, lovasz_softmax
from occgen.metrics import OccupancyIoU


def _iou(pred, target, c):
    inter = ((pred == c) & (target == c)).sum().item()
    union = ((pred == c) | (target == c)).sum().item()
    return inter / union


def test_lovasz_of_one_hot_predictions_is_the_mean_jaccard_loss():
    gen = torch.Generator().manual_seed(1)
    target = torch.randint(0, 4, (500,), generator=gen)
    pred = torch.where(torch.rand(500, generator=gen) < 0.3, torch.randint(0, 4, (500,), generator=gen), target)
    probs = torch.nn.functional.one_hot(pred, 5).float()
    expected = sum(1 - _iou(pred, target, c) for c in range(4)) / 4
    assert abs(lovasz_softmax(probs, target).item() - expected) < 1e-6


def test_lovasz_is_zero_for_a_perfect_prediction_and_has_gradients():
    target = torch.tensor([0, 1, 1, 2, 2, 2])
    assert lovasz_softmax(torch.nn.functional.one_hot(target, 3).float(), target).item() == 0.0
    logits = torch.zeros(6, 3, requires_grad=True)
    lovasz_softmax(logits.softmax(1), target).backward()
    assert logits.grad.abs().sum() > 0


def test_kl_is_zero_for_the_prior_and_positive_otherwise():
    assert kl_divergence(torch.zeros(10), torch.zeros(10)).item() == 0.0
    assert kl_divergence(torch.ones(10), torch.zeros(10)).item() == 0.5


def test_iou_and_miou_against_hand_counts():
    target = torch.tensor([0, 0, 12, 12, 2, 2, 13])
    pred = torch.tensor([0, 12, 12, 0, 2, 13, 13])
    meter = OccupancyIoU()
    meter.update(pred, target)
    out = meter.compute()
    assert out["iou"] == 4 / 6  # occupied: target {2..6}, pred {1,2,4,5,6}
    assert out["per_class"] == {2: 1 / 2, 12: 1 / 3, 13: 1 / 2}
    assert abs(out["miou"] - (1 / 2 + 1 / 3 + 1 / 2) / 3) < 1e-12
