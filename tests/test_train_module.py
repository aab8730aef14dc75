"""Lightning training of the contact models: non-finite steps are skipped, resume continues exactly."""

from __future__ import annotations

import lightning.pytorch as pl
import pytest
import torch
from test_models import _colliding_chunks
from torch.utils.data import DataLoader, TensorDataset

import diffcontact as dc
from diffcontact.train.config import TrainConfig
from diffcontact.train.module import ContactLightningModule

# (these tests fit the module on a training loader alone: Lightning's notice that validation is skipped is expected)
pytestmark = pytest.mark.filterwarnings("ignore:You defined a `validation_step` but have no `val_dataloader`")


def _loader(seed: int = 0) -> DataLoader:
    X, V = _colliding_chunks(dc.build_task("BP1"), 16, seed=seed)
    return DataLoader(TensorDataset(X.float(), V.float()), batch_size=8)


def _trainer(**kw) -> pl.Trainer:
    return pl.Trainer(logger=False, enable_progress_bar=False, enable_model_summary=False, deterministic=True, **kw)


def _module() -> ContactLightningModule:
    return ContactLightningModule(
        TrainConfig("BP1", hidden=8, layers=1, mu_transform="softplus", e_transform="sigmoid", schedule="constant")
    )


def test_a_step_with_non_finite_gradients_is_skipped_entirely():
    module = _module()
    before = {k: v.clone() for k, v in module.net.state_dict().items()}

    def poisoned_loss(batch):
        return module.net.params.mu_raw.sum() * float("nan")

    module.loss = poisoned_loss
    _trainer(max_epochs=1, enable_checkpointing=False).fit(module, _loader())
    after = module.net.state_dict()
    assert module.skipped_steps == 2  # two batches, both skipped
    assert all(torch.equal(before[k], after[k]) for k in before)  # no update, no weight decay


@pytest.mark.filterwarnings("ignore:Be aware that when using `ckpt_path`")  # (resumed without the checkpoint callback)
def test_resume_continues_from_the_saved_epoch_with_the_same_optimiser_state(tmp_path):
    torch.manual_seed(0)
    straight = _module()
    _trainer(max_epochs=4, enable_checkpointing=False).fit(straight, _loader())

    torch.manual_seed(0)
    first = _module()
    ckpt = pl.callbacks.ModelCheckpoint(dirpath=tmp_path, save_last=True, every_n_epochs=1, save_top_k=-1)
    _trainer(max_epochs=2, callbacks=[ckpt]).fit(first, _loader())
    resumed = _module()
    _trainer(max_epochs=4, enable_checkpointing=False).fit(resumed, _loader(), ckpt_path=str(tmp_path / "last.ckpt"))
    assert resumed.current_epoch == straight.current_epoch == 4
    for k, v in straight.net.state_dict().items():
        assert torch.allclose(v, resumed.net.state_dict()[k], rtol=1e-5, atol=1e-6), k


def test_a_step_whose_forward_pass_fails_is_skipped_and_counted_with_a_warning(caplog):
    """A forward pass that ends in a non-finite state (FloatingPointError from the simulator) skips its step as
    non-finite gradients do, with one warning naming it; training continues."""
    module = _module()
    real, calls = module.loss, []

    def diverging_once(batch):
        calls.append(1)
        if len(calls) == 1:
            raise FloatingPointError("BP1 frame 3: non-finite position or velocity in batch element 0")
        return real(batch)

    module.loss = diverging_once
    before = {k: v.clone() for k, v in module.net.state_dict().items()}
    with caplog.at_level("WARNING", logger="diffcontact.train.module"):
        trainer = _trainer(max_epochs=1, enable_checkpointing=False, limit_val_batches=0)
        trainer.fit(module, _loader())
    assert torch.isfinite(trainer.callback_metrics["train/loss"])  # (the epoch's loss: the step that ran)
    assert module.skipped_steps == 1 and module.forward_failures == 1 and len(calls) == 2
    totals = module.totals()
    assert totals["skipped_steps"] == 1 and totals["forward_failures"] == 1 and totals["solver_failures"] == 0
    assert any(not torch.equal(before[k], v) for k, v in module.net.state_dict().items())  # (the second step ran)
    warned = [r.getMessage() for r in caplog.records if "training step skipped" in r.getMessage()]
    assert warned == ["epoch 0 batch 0: training step skipped: its forward pass failed (BP1 frame 3: non-finite "
                      "position or velocity in batch element 0)"]  # fmt: skip


def test_the_mu_pull_moves_mu_off_the_sticking_plateau():
    """With μ far above the truth every contact sticks and the data give μ no gradient (a plateau); the L1 pull
    (``mu_l1``) gives a constant one, which Adam follows at its full rate, and only in training."""
    X, V = _colliding_chunks(dc.build_task("BP1"), 16, seed=0)
    batch = (X.double(), V.double())

    def descend(mu_l1: float) -> tuple[float, float]:
        module = ContactLightningModule(TrainConfig("BP1", hidden=8, layers=1, mu_l1=mu_l1, dtype="float64")).train()
        for p in module.net.parameters():
            p.requires_grad_(False)
        mu = module.learned.mu_raw
        mu.requires_grad_(True)
        with torch.no_grad():
            mu.fill_(50.0)
        data = module.loss(batch) - mu_l1 * module.learned.mu.sum()
        (grad,) = torch.autograd.grad(data, mu)
        opt = torch.optim.Adam([mu], lr=0.05)
        for _ in range(4):
            opt.zero_grad()
            module.loss(batch).backward()
            opt.step()
        return float(grad.abs().max()), float(mu.detach().max())

    plateau_grad, mu_without = descend(0.0)
    assert plateau_grad < 1e-12 and mu_without == pytest.approx(50.0, abs=1e-9)  # (every contact sticks)
    _, mu_with = descend(1e-6)
    assert mu_with == pytest.approx(50.0 - 4 * 0.05, abs=1e-3)  # (Adam's steps: lr each, whatever the pull's size)
    module = ContactLightningModule(TrainConfig("BP1", hidden=8, layers=1, mu_l1=1.0, dtype="float64")).eval()
    plain = ContactLightningModule(TrainConfig("BP1", hidden=8, layers=1, dtype="float64")).eval()
    assert torch.equal(module.loss(batch), plain.loss(batch))  # (validation: the data's loss alone)
