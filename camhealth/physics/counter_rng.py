"""Counter-based random fields: uniform and standard-normal draws as a pure function of (keys, element index).

Torch's CPU generator (Mersenne Twister) produces one number after another on one core: a 32×1×192×192
``randn`` costs ~5 ms here, ``rand`` ~5 ms, and the sensor-noise chain needs three such fields per batch.
A counter-based generator computes draw ``i`` directly as a hash of ``i`` and a per-call key, so a whole
field is one element-wise expression that :func:`torch.compile` turns into a single vectorised, multi-threaded
loop (1.3 ms for the same field here), fused with the arithmetic that uses it. The same numbers can be
recomputed at any subset of indices (the exact-Poisson pass of :func:`~camhealth.physics.image_formation.
sample_poisson` needs the normals of its own pixels only), and the eager and compiled versions give the same
integers, hence the same uniforms, and normals that agree to float rounding of ``log``/``cos``.

Construction. Bits are 32-bit words held in int32 tensors (multiplication wraps modulo 2³², right shifts are
masked to act as logical shifts). The mixing function is the two-multiply integer finaliser ("lowbias32"):

    x ^= x >> 16;  x *= 0x7feb352d;  x ^= x >> 15;  x *= 0x846ca68b;  x ^= x >> 16

— a bijection of the 32-bit words with near-ideal avalanche. Element ``i`` (flat index, < 2³¹) of a field
with keys (k₀, k₁, k₂) draws ``h = f(i ⊕ k₀)``, then ``a = f(h ⊕ k₁)`` and ``b = f(h ⊕ k₂)``; a uniform uses
the top 24 bits of ``a`` (multiples of 2⁻²⁴ in [0, 1), the grid of torch's float32 ``rand``), a normal is
the Box–Muller transform z = √(−2 ln u₁)·cos(2π u₂) with u₁ = (a₂₄ + ½)·2⁻²⁴ ∈ (0, 1) and u₂ = b₂₄·2⁻²⁴.
u₁ ≥ 2⁻²⁵ caps |z| at 5.9 (probability of a larger |z| under N(0, 1): 4·10⁻⁹, i.e. one pixel in ~60 batches of
32×192×192 would have been larger). Keys come from the caller's :class:`torch.Generator` (three int32 per
field), so a seeded generator reproduces every field exactly.

Dtypes: draws are computed in float32 or float64. For float16/bfloat16 they are computed in float32 and rounded
to the requested dtype at the end (uniforms are then capped at the largest number below 1 of that dtype, so
they stay in [0, 1); normals stay finite, |z| ≤ 5.9).

Statistics are tested (``tests/physics/test_counter_rng.py``): moments, χ² of the uniform histogram,
normal quantiles (Kolmogorov–Smirnov), and correlation between neighbouring pixels, between the two draws of
one pixel and between fields of different keys.

Compilation: each public function runs a :func:`torch.compile`-d kernel (inductor, dynamic shapes; a C++
compiler is needed on CPU, which the machines camhealth supports have). If compilation fails, a warning is
issued once and the eager expression is used from then on (same integers, ~4× slower than torch's RNG);
``CAMHEALTH_COMPILE=0`` in the environment forces the eager path.
"""

from __future__ import annotations

import os
import warnings
from typing import Callable, Sequence

import torch

__all__ = [
    "LazyCompiled", "check_counter_size", "compiled", "counter_bits24", "counter_keys", "counter_normal", "counter_normal_at", "counter_normal_expr", "counter_uniform",
    "counter_uniform_at",
]

#: Largest field size: flat element indices are int32.
MAX_ELEMENTS = 2**31 - 1

_M1 = 0x7FEB352D
_M2 = 0x846CA68B - 2**32  # the same 32-bit word as a signed int32
_INV24 = 1.0 / 16777216.0
_TWO_PI = 6.283185307179586


def _mix(v: torch.Tensor) -> torch.Tensor:
    """lowbias32 finaliser on int32-held 32-bit words (wrapping multiplies, logical shifts by masking)."""
    v = v ^ ((v >> 16) & 0xFFFF)
    v = v * _M1
    v = v ^ ((v >> 15) & 0x1FFFF)
    v = v * _M2
    return v ^ ((v >> 16) & 0xFFFF)


def counter_bits24(index: torch.Tensor, keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The two 24-bit words (int32 in [0, 2²⁴)) of the elements ``index`` (int32) of the field ``keys``; an
    element-wise expression for use inside other compiled kernels (the uniform is the first word × 2⁻²⁴)."""
    h = _mix(index ^ keys[0])
    return (_mix(h ^ keys[1]) >> 8) & 0xFFFFFF, (_mix(h ^ keys[2]) >> 8) & 0xFFFFFF


def _work_dtype(dtype: torch.dtype) -> torch.dtype:
    """Compute dtype of the draws: float32/float64 as requested, float32 for the half-precision dtypes (a 24-bit
    integer in float16 overflows, and both half formats round the 2⁻²⁴ grid up to 1.0)."""
    return dtype if dtype in (torch.float32, torch.float64) else torch.float32


def _check_dtype(dtype: torch.dtype) -> torch.dtype:
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point or dtype.is_complex:
        raise TypeError(f"dtype must be a floating torch.dtype (float16, bfloat16, float32 or float64), got {dtype}")
    return dtype


def _uniform_as(u: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Work-dtype uniforms in ``dtype``, capped below 1 (rounding to a half format can round 1 − 2⁻²⁴ up to 1)."""
    if u.dtype == dtype:
        return u
    out = u.to(dtype)
    below_one = torch.nextafter(torch.ones((), dtype=dtype, device=out.device), torch.zeros((), dtype=dtype, device=out.device))
    return out.clamp_(max=below_one)


def counter_normal_expr(index: torch.Tensor, keys: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """The standard normals of the elements ``index`` (int32) of the field ``keys`` as an element-wise
    expression, for use inside other compiled kernels (computed in float32 for half-precision ``dtype``)."""
    wd = _work_dtype(dtype)
    a, b = counter_bits24(index, keys)
    u1 = (a.to(wd) + 0.5) * _INV24
    u2 = b.to(wd) * _INV24
    z = torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(_TWO_PI * u2)
    return z if wd == dtype else z.to(dtype)


# ---------------------------------------------------------------------------------------------- kernels
def _k_uniform(n: int, keys: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    a, _ = counter_bits24(torch.arange(n, dtype=torch.int32, device=keys.device), keys)
    return a.to(dtype) * _INV24


def _k_normal(n: int, keys: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    return counter_normal_expr(torch.arange(n, dtype=torch.int32, device=keys.device), keys, dtype)


def _k_normal_scaled(scale: torch.Tensor, n_per_row: int, keys: torch.Tensor) -> torch.Tensor:
    """(R, n) normals times a per-row scale (R, 1): one fused pass."""
    r = scale.shape[0]
    idx = torch.arange(r * n_per_row, dtype=torch.int32, device=keys.device).view(r, n_per_row)
    return counter_normal_expr(idx, keys, scale.dtype) * scale


def _k_uniform_at(index: torch.Tensor, keys: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    a, _ = counter_bits24(index.to(torch.int32), keys)
    return a.to(dtype) * _INV24


def _k_normal_at(index: torch.Tensor, keys: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    return counter_normal_expr(index.to(torch.int32), keys, dtype)


class LazyCompiled:
    """A kernel compiled (:func:`torch.compile`, dynamic shapes) on first use; if compilation or the compiled
    call fails, a warning is issued once and the eager function is used from then on."""

    def __init__(self, fn: Callable[..., torch.Tensor]) -> None:
        self.fn = fn
        self._compiled: Callable[..., torch.Tensor] | None = None
        self._failed = False

    def __call__(self, *args, **kwargs) -> torch.Tensor:
        if self._failed or not compiled():
            return self.fn(*args, **kwargs)
        if self._compiled is None:
            self._compiled = torch.compile(self.fn, dynamic=True)
        try:
            return self._compiled(*args, **kwargs)
        except Exception as err:  # a missing or broken C++ toolchain surfaces here, on the first call
            self._failed = True
            warnings.warn(
                f"camhealth: torch.compile of the counter-based RNG kernel {self.fn.__name__} failed "
                f"({type(err).__name__}: {str(err).splitlines()[0][:200] if str(err) else ''}); using the eager "
                "expression (same numbers, slower)", RuntimeWarning, stacklevel=2,
            )
            return self.fn(*args, **kwargs)


def compiled() -> bool:
    """Whether the kernels are compiled (``CAMHEALTH_COMPILE`` unset or not ``0``)."""
    return os.environ.get("CAMHEALTH_COMPILE", "1").strip() not in ("0", "false", "False", "no")


_uniform = LazyCompiled(_k_uniform)
_normal_field = LazyCompiled(_k_normal)
_normal_scaled = LazyCompiled(_k_normal_scaled)
_normal_at = LazyCompiled(_k_normal_at)
_uniform_at = LazyCompiled(_k_uniform_at)


# ---------------------------------------------------------------------------------------------- API
def counter_keys(generator: torch.Generator | None = None, device: torch.device | str | None = None) -> torch.Tensor:
    """Three int32 keys for one field, drawn from ``generator`` (torch's default generator if ``None``)."""
    gdev = generator.device if generator is not None else torch.device("cpu")
    keys = torch.randint(-(2**31), 2**31, (3,), generator=generator, dtype=torch.int64, device=gdev)
    return keys.to(torch.int32).to(device if device is not None else gdev)


def check_counter_size(n: int) -> int:
    """``n`` if a counter-based field of ``n`` elements fits the int32 element indices, else a ValueError."""
    if n > MAX_ELEMENTS:
        raise ValueError(f"counter-based fields hold at most {MAX_ELEMENTS} elements (int32 indices), got {n}; "
                         "use rng='torch' for larger batches")
    return n


def _numel(shape: Sequence[int]) -> int:
    n = 1
    for d in shape:
        n *= int(d)
    return check_counter_size(n)


def counter_uniform(shape: Sequence[int], keys: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Uniform draws in [0, 1) on the 2⁻²⁴ grid, of ``shape``, on the keys' device (for float16/bfloat16: those
    draws rounded to ``dtype``, capped below 1)."""
    wd = _work_dtype(_check_dtype(dtype))
    return _uniform_as(_uniform(_numel(shape), keys, wd), dtype).view(*shape)


def counter_normal(
    shape: Sequence[int], keys: torch.Tensor, dtype: torch.dtype = torch.float32, scale: torch.Tensor | None = None
) -> torch.Tensor:
    """Standard-normal draws of ``shape`` (B, …), multiplied by a per-sample ``scale`` (B,) if given (computed in
    float32 for float16/bfloat16 ``dtype``, then rounded to it)."""
    wd = _work_dtype(_check_dtype(dtype))
    n = _numel(shape)
    if scale is None:
        return _normal_field(n, keys, wd).view(*shape).to(dtype)
    b = int(shape[0])
    scale = scale.to(device=keys.device, dtype=wd).reshape(-1)
    if scale.shape[0] != b:
        raise ValueError(f"scale must have one value per sample ({b}), got {scale.shape[0]}")
    return _normal_scaled(scale.view(b, 1), n // max(b, 1), keys).view(*shape).to(dtype)


def counter_uniform_at(index: torch.Tensor, keys: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The uniforms of a field with ``keys`` at the flat element indices ``index`` (integers in [0, 2³¹))."""
    wd = _work_dtype(_check_dtype(dtype))
    return _uniform_as(_uniform_at(index, keys, wd), dtype)


def counter_normal_at(index: torch.Tensor, keys: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The normals of a field with ``keys`` at the flat element indices ``index`` (integers in [0, 2³¹))."""
    wd = _work_dtype(_check_dtype(dtype))
    return _normal_at(index, keys, wd).to(dtype)
