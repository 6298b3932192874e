"""Real collection on Ray: TorchRL's ``RayCollector`` stepping the robots in Ray actors.

Training over many robots (many designs, many morphologies) is where a user outgrows one
machine's processes. TorchRL's ``RayCollector`` runs one ``Collector`` per Ray actor, on a local
Ray cluster or on one a scheduler started (``collector.ray_address``), gathers one batch from
each per iteration and sends the policy's weights to them when asked. This module adds the two
things our epochs need from it, as the multi-process path already has them:

* :class:`SeededCollector`: each actor's ``set_seed`` also seeds the actor's torch (the policy's
  action noise) and restarts its robots, so an epoch is a function of the epoch's seed on Ray
  as in one process, and a resumed run continues exactly;
* :class:`EpochRayCollector`: a ``RayCollector`` that shuts down the local Ray cluster it started
  when it is shut down, and leaves a cluster it joined running.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable, Sequence

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.collectors.distributed import RayCollector

BACKENDS = ("process", "ray")


class SeededCollector(Collector):
    """A ``Collector`` whose ``set_seed`` seeds its env, its process's torch, and resets its robots.

    In one process, :class:`~unipolicy_rl.collectors.RealEpochCollector` does the last two
    itself; a collector in a Ray actor has no one else in its process to do them.
    """

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        next_seed = super().set_seed(seed, static_seed)
        torch.manual_seed(seed)
        self.reset()
        return next_seed


class EpochRayCollector(RayCollector):
    """A ``RayCollector`` that shuts down the local cluster it started (not one it joined)."""

    def __init__(self, *args, owns_cluster: bool, **kwargs) -> None:
        self._owns_cluster = owns_cluster
        super().__init__(*args, **kwargs)

    def shutdown(self, timeout: float | None = None, shutdown_ray: bool = False) -> None:
        super().shutdown(timeout=timeout, shutdown_ray=shutdown_ray or self._owns_cluster)


def require_ray(address: str | None = None):
    """``ray``, or an ImportError that says how to get it; for a ``ray://`` ``address``, with the
    client Ray connects there through (``ray[client]``)."""
    try:
        import ray
    except ImportError as error:
        raise ImportError("collector.backend=ray needs Ray: pip install 'unipolicy_rl[ray]' (or pip install ray)") \
            from error
    if address is not None and str(address).startswith("ray://") and importlib.util.find_spec("grpc") is None:
        raise ImportError(f"collector.ray_address={address} joins a cluster through Ray's client, which is not "
                          f"installed: pip install 'unipolicy_rl[ray]' (or pip install 'ray[client]')")
    return ray


def make_epoch_ray_collector(env_factories: Sequence[Callable], policy: TensorDictModuleBase, *,
                             frames_per_batch: int, total_frames: int, postproc: Callable,
                             address: str | None = None, cpus_per_worker: float = 1.0):
    """One ``SeededCollector`` per entry of ``env_factories``, each in a Ray actor.

    ``address``: a running Ray cluster to join (``auto``, or ``ray://host:port``); None starts a
    local one with a CPU per worker, shut down with the collector. Each batch stacks the
    workers' batches (``[workers, robots, steps]``), as the multi-process collector's does.
    """
    ray = require_ray(address)
    owns_cluster = address is None and not ray.is_initialized()
    init = {"address": address, "ignore_reinit_error": True, "include_dashboard": False, "log_to_driver": False,
            "configure_logging": False}
    if owns_cluster:
        init["num_cpus"] = max(1, round(cpus_per_worker * len(env_factories)))
    try:
        collector = EpochRayCollector(list(env_factories), policy, owns_cluster=owns_cluster,
                                      frames_per_batch=frames_per_batch, total_frames=total_frames,
                                      collector_class=SeededCollector, sync=True, postproc=postproc,
                                      ray_init_config=init,
                                      remote_configs={"num_cpus": cpus_per_worker, "num_gpus": None, "memory": None})
    except ConnectionError as error:  # ray.init: no cluster at the address
        raise ConnectionError(f"collector.ray_address={address}: no Ray cluster answers there ({error}); start one "
                              f"(ray start --head) or give its address, or set collector.ray_address=null for a "
                              f"local cluster") from None
    collector.update_policy_weights_()  # connects the weight sync before the first batch
    return collector
