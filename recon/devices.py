"""Which implementation serves a tensor: the numba CPU kernels or their pure-torch twins.

Every fast path that has a CPU kernel dispatches through `uses_cpu_kernels`, so one switch
sends all of them to the torch twins: the path every non-CPU device takes. The device-leak test
(`tests/models/test_device_clean.py`) turns it off to run a GPU's code path on the CPU and watch it
for host round trips.

Below every layer of the package: it imports nothing from recon.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import torch
from torch import Tensor

T = TypeVar("T")


def uses_cpu_kernels(t: Tensor) -> bool:
    """True when `t` lives on the CPU, where the numba kernels run; False elsewhere (CUDA):
    the torch twins, which never copy to the host."""
    return t.device.type == "cpu"


def masked(mask: Tensor, *tensors: Tensor) -> tuple[Tensor, ...]:
    """(t[mask] for t in tensors), the (N,) bool `mask` read back once: each boolean index
    reads its mask's count on the host, a wait for the GPU's queue. Example: mask [T, F, T],
    tensors [1, 2, 3] and [[1], [2], [3]] -> ([1, 3], [[1], [3]])."""
    index = mask.nonzero()[:, 0]
    return tuple(t.index_select(0, index) for t in tensors)


def generator_on(generator: torch.Generator, device: torch.device) -> torch.Generator:
    """`generator` itself when it already draws on `device`, else a new one there seeded with
    its initial seed (a generator's state cannot cross device types: CPU Mersenne Twister,
    CUDA Philox). Random numbers are then drawn where they are used, with no host copy."""
    if generator.device == device:
        return generator
    return torch.Generator(device=device).manual_seed(generator.initial_seed())


def host_value(owner: object, key: str, tensor: Tensor, read: Callable[[Tensor], T]) -> T:
    """read(tensor), a value on the host (a sync on a GPU), kept on `owner` under `key` and read
    again only once `tensor` is another tensor or was written in place (its version counter
    moved: fill_, copy_, a load_state_dict): a training step reads a buffer's value without a
    host round trip."""
    cache = owner.__dict__.setdefault("_host_values", {})
    made = cache.get(key)
    if made is None or made[0] is not tensor or made[1] != tensor._version:
        made = cache[key] = (tensor, tensor._version, read(tensor))
    return made[2]
