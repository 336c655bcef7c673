"""The denoiser's training loop written out: the slow obvious reference of `denoise.n2v.optimise_unet`."""

import torch

from denoise.model import N2VModel
from denoise.n2v import N2VConfig, chunk_bounds, lr_factor


def reference_training(model: N2VModel, config: N2VConfig, batch_at_step, *, chunks: int = 1) -> N2VModel:
    """Adam at `config.lr` with the warm-up and cosine schedule, `config.steps` steps, no divergence guard; each
    step's `StepBatch` split into `chunks` (`chunk_bounds`), the chunks' share-weighted losses backpropagated one
    after the other through the one network (gradients accumulated in chunk order); the step's loss appended to
    `model.history`. Returns `model` in eval mode."""
    opt = torch.optim.Adam(model.unet.parameters(), lr=config.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(
        s, steps=config.steps, warmup_frac=config.warmup_frac, min_lr_frac=config.min_lr_frac))
    model.unet.train()
    for step in range(config.steps):
        batch = batch_at_step(step)
        n = int(batch.rows[0].shape[0])
        opt.zero_grad(set_to_none=True)
        total = 0.0
        for start, stop in chunk_bounds(n, chunks):
            loss = batch.loss(model.unet, *(t[start:stop] for t in batch.rows)) * ((stop - start) / n)
            loss.backward()
            total += loss.item()
        opt.step()
        sched.step()
        model.history.append(total)
    model.unet.eval()
    return model
