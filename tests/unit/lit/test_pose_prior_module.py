"""PosePriorModule: its loss reads the rotation block and the translation column, its rre is batch-size weighted."""

from types import SimpleNamespace

import pytest
import torch

from anycity.lit.pose_prior import PosePriorModule
from anycity.structures import ViewBatch


def _batch(b: int, v: int = 3) -> ViewBatch:
    """``b`` samples of ``v`` identity views ([b, v, 4, 4] w2c), 16x16 images."""
    w2c = torch.eye(4).repeat(b, v, 1, 1)
    return ViewBatch(context=SimpleNamespace(images=torch.rand(b, v, 3, 16, 16), w2c=w2c), target=None)


def test_the_loss_is_l1_on_the_rotation_block_plus_the_translation_column(monkeypatch):
    """A prediction off by +1 in every translation component and exact in rotation costs 0 + 1; the bottom row
    (0, 0, 0, 1), equal in both, must not stand in for the translation."""
    m = PosePriorModule(channels=8, grid=4)
    batch = _batch(2)

    def shifted(images):
        w2c = torch.eye(4).repeat(*images.shape[:2], 1, 1)
        w2c[..., :3, 3] += 1.0
        return w2c

    monkeypatch.setattr(m.net, "forward", shifted)
    assert float(m.loss(batch)) == pytest.approx(1.0)


def test_the_logged_val_rre_is_weighted_by_batch_size(monkeypatch):
    """Batches of 2 samples at 10 degrees and 1 at 40: the mean over samples is 20, not the mean of batch means
    (25)."""
    import anycity.lit.pose_prior as pose_prior_module

    m = PosePriorModule(channels=8, grid=4)
    m._trainer = SimpleNamespace(world_size=1)
    logged = {}
    monkeypatch.setattr(m, "log", lambda name, value, **k: logged.__setitem__(name, float(value)))
    errors = iter([torch.full((2, 3), 10.0), torch.full((1, 3), 40.0)])  # [B, P] degrees, P = 3 pairs of 3 views
    monkeypatch.setattr(pose_prior_module, "relative_pose_errors", lambda pred, gt: (next(errors), None))
    with torch.no_grad():
        m.on_validation_epoch_start()
        m.validation_step(_batch(2), 0)
        m.validation_step(_batch(1), 1)
        m.on_validation_epoch_end()
    assert logged == {"val/rre": pytest.approx(20.0)}
