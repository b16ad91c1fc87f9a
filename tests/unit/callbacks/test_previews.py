"""ImagePreviews: nothing written under fast_dev_run; the every_n_val cadence survives a resume."""

from types import SimpleNamespace

import torch

from anycity.callbacks import ImagePreviews

OUT = {"preview": {"context": torch.rand(2, 3, 8, 8), "target": torch.rand(2, 3, 8, 8)}}


def _trainer(root, step, fast_dev_run=0, is_global_zero=True, sanity_checking=False):
    calls = []
    logger = SimpleNamespace(log_dir=None, log_image=lambda **kw: calls.append(kw))  # fast_dev_run's stand-in
    return SimpleNamespace(is_global_zero=is_global_zero, global_step=step, sanity_checking=sanity_checking,
                           fast_dev_run=fast_dev_run, default_root_dir=str(root), logger=logger, loggers=[logger],
                           calls=calls)


def test_fast_dev_run_writes_no_preview(tmp_path):
    cb = ImagePreviews()
    trainer = _trainer(tmp_path, 1, fast_dev_run=1)
    cb.on_validation_batch_end(trainer, None, OUT, None, 0)
    cb.on_test_batch_end(trainer, None, OUT, None, 0)
    assert list(tmp_path.iterdir()) == [] and trainer.calls == [] and cb.last_path is None


def test_every_n_val_cadence_survives_a_resume(tmp_path):
    cb = ImagePreviews(every_n_val=2)
    cb.on_validation_batch_end(_trainer(tmp_path, 10), None, OUT, None, 0)  # 1st validation: written
    assert cb.last_path.name == "val_step000010.png"
    resumed = ImagePreviews(every_n_val=2)
    resumed.load_state_dict(cb.state_dict())  # what Lightning does with the checkpoint's callback state
    resumed.on_validation_batch_end(_trainer(tmp_path, 20), None, OUT, None, 0)  # 2nd: skipped
    assert resumed.last_path is None
    resumed.on_validation_batch_end(_trainer(tmp_path, 30), None, OUT, None, 0)  # 3rd: written
    assert resumed.last_path.name == "val_step000030.png"
    assert sorted(p.name for p in (tmp_path / "previews").iterdir()) == ["val_step000010.png", "val_step000030.png"]


def test_only_global_rank_zero_writes_a_preview(tmp_path):
    cb = ImagePreviews()
    trainer = _trainer(tmp_path, 10, is_global_zero=False)
    cb.on_validation_batch_end(trainer, None, OUT, None, 0)
    cb.on_test_batch_end(trainer, None, OUT, None, 0)
    assert list(tmp_path.iterdir()) == [] and trainer.calls == [] and cb.last_path is None


def test_the_sanity_check_writes_no_preview_and_keeps_the_cadence(tmp_path):
    cb = ImagePreviews(every_n_val=2)
    cb.on_validation_batch_end(_trainer(tmp_path, 0, sanity_checking=True), None, OUT, None, 0)
    assert cb.last_path is None and list(tmp_path.iterdir()) == []
    cb.on_validation_batch_end(_trainer(tmp_path, 10), None, OUT, None, 0)  # the 1st real validation: written
    assert sorted(p.name for p in (tmp_path / "previews").iterdir()) == ["val_step000010.png"]
