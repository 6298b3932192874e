"""Adam on the fused kernel takes Adam's step; parameters the kernel cannot take get the default one."""

import torch

from unipolicy_rl.cpu_speed.fused_adam import adam


def steps_taken(optimizer_of, seed: int = 0) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    params = [torch.nn.Parameter(torch.randn(7, 20, 30, generator=generator)),
              torch.nn.Parameter(torch.randn(7, 1, 30, generator=generator))]
    optimizer = optimizer_of(params)
    for _ in range(5):
        optimizer.zero_grad()
        loss = sum((p ** 2).sum() * (i + 1) for i, p in enumerate(params))
        loss.backward()
        optimizer.step()
    return [p.detach() for p in params]


def test_adam_on_cpu_runs_fused_and_moves_the_weights_as_the_default_kernel_does():
    settings = dict(lr=1e-2, weight_decay=1e-3)
    fused = steps_taken(lambda params: adam(params, **settings))
    default = steps_taken(lambda params: torch.optim.Adam(params, **settings))
    probe = adam([torch.nn.Parameter(torch.zeros(3))], lr=1.0)
    assert probe.defaults["fused"] is True
    for a, b in zip(fused, default, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_adam_takes_the_default_kernel_where_the_fused_one_cannot_run():
    on_meta = adam([torch.nn.Parameter(torch.zeros(3, device="meta"))], lr=1.0)
    assert not on_meta.defaults["fused"]
    mixed = adam([torch.nn.Parameter(torch.zeros(3)), torch.nn.Parameter(torch.zeros(3, device="meta"))], lr=1.0)
    assert not mixed.defaults["fused"]
