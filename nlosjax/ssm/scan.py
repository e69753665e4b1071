"""Selective scan (Mamba v1 S6) kernels: associative, sequential and chunked.

For one sequence of ``L`` steps, ``Dch`` channels and ``N`` states per channel,

.. math::

    h_t = \\exp(\\Delta_t A) \\odot h_{t-1} + \\Delta_t x_t B_t^\\top, \\qquad
    y_t = h_t C_t + D \\odot x_t,

with ``h_t`` ``[Dch, N]``, ``A`` ``[Dch, N]`` (<= 0, so the decay lies in
(0, 1]), ``B_t, C_t`` ``[N]`` shared by all channels, ``dt_t = Delta_t > 0``
and ``x_t`` ``[Dch]``. ``A`` is discretised by zero-order hold and ``B`` by
Euler, exactly as Mamba's ``selective_scan_ref`` and CUDA kernel do
(Gu & Dao 2023, arXiv:2312.00752; state-spaces/mamba #114).
``reverse=True`` runs the same recurrence from the last step to the first
(``h_t`` depends on ``h_{t+1}``): it equals flipping every input along time,
scanning causally and flipping the output back.

Methods (all exact; they differ in speed and memory):

* ``"associative"``: materialise the pairs ``(a_t, b_t) = (exp(dt_t A),
  dt_t x_t B_t)`` ``[L, ..., Dch, N]`` and combine them with
  ``jax.lax.associative_scan`` (depth ``ceil(log2 L)``).
* ``"sequential"``: ``jax.lax.scan`` over time whose step discretises,
  updates the state and contracts it with ``C_t``; only the state
  ``[..., Dch, N]`` lives between steps, nothing ``[..., L, Dch, N]`` is built.
* ``"chunked"``: an outer ``lax.scan`` over chunks of ``chunk_size`` steps that
  carries the state, an associative scan inside each chunk (8 steps by default:
  at (64, 512, 32, 16) and (128, 256, 32, 16) on 2 cores, 8 steps ran forward
  and forward+backward about 1.5x faster than 64, with a quarter of the memory).
* ``"blockwise"``: time in blocks of ``chunk_size`` steps, all blocks at once:
  each block's affine summary from a zero state (one fused scan over its
  steps, batched over blocks; the decay product in closed form), an
  associative scan over the summaries for the state entering every block
  (log depth across blocks), then each block rerun from its entering state,
  contracting with ``C`` as it goes. The forward builds nothing
  ``[L, ..., N, Dch]``; about twice the exponentials of "sequential". Its
  backward has the same structure (block summaries of the adjoint, a reverse
  associative scan over blocks), then forms each block's cotangents step by
  step, one block at a time, so that one block's ``[K, ..., N, Dch]`` states
  are the largest transient. Block size 64 by default.
* ``"auto"``: chosen per backend and scan size by :func:`resolve_method` from
  the numbers in ``benchmarks/results/scan.md`` (CPU) and ``device.md`` (GPU).

Gradients of every method come from one custom VJP whose residuals are the
inputs and, for "sequential" and "chunked", the states entering each chunk
(``[ceil(L / chunk), ..., Dch, N]``). The backward pass walks the chunks in the
opposite order, recomputes the states of one chunk from its entering state and
runs the adjoint recurrence ``g_t = C_t gy_t + a_{t+1} g_{t+1}`` with the same
kernel (a fused reverse ``lax.scan`` or a reverse associative scan), then forms
every cotangent in closed form. So a differentiated "sequential"/"chunked" call
holds at most one chunk of states at a time and keeps nothing of size
``[..., L, Dch, N]`` for the backward pass; "associative" treats the whole
sequence as one chunk (its backward, like its forward, builds ``[L, ..., Dch, N]``
arrays, but only transiently -- nothing of that size is saved between the
passes). Forward-mode autodiff (``jax.jvp``) is not supported.

Internally everything is time-major and the state is laid out
``[..., N, Dch]`` (channels minor), which XLA:CPU vectorises best.

State and accumulation are float32 for float16/bfloat16/float32 inputs (float64
when the inputs are float64 and x64 is enabled); ``y`` is returned in the dtype
of ``x``, the final state in the accumulation dtype.

Stability: the decay ``exp(dt A)`` is in (0, 1] for ``dt >= 0`` and ``A <= 0``,
so products of decays underflow to 0 (harmless) and never overflow; no
division by a decay appears anywhere (unlike reverse-recomputation schemes).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

METHODS = ("associative", "sequential", "chunked", "blockwise", "auto")
COMBINES = ("mean", "sum", "none")
DEFAULT_CHUNK = {"sequential": 64, "chunked": 8, "blockwise": 64}


# ------------------------------------------------------------------ validation
def _is_concrete(v) -> bool:
  return not isinstance(v, jax.core.Tracer)


def _shape_of(v, name: str) -> tuple[int, ...]:
  dtype = getattr(v, "dtype", None)
  if dtype is None or not jnp.issubdtype(dtype, jnp.floating):
    raise ValueError(f"{name} must be a real floating-point array, got dtype {dtype}")
  return tuple(v.shape)


def _check_inputs(x, dt, A, B, C, D, initial_state, method, chunk_size):
  """Shapes, dtypes, method and (for concrete values) ranges; ValueError naming the argument."""
  if method not in METHODS:
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")
  if chunk_size is not None and not (isinstance(chunk_size, (int, np.integer))
                                     and not isinstance(chunk_size, bool) and chunk_size >= 1):
    raise ValueError(f"chunk_size must be a positive integer or None, got {chunk_size!r}")
  xs = _shape_of(x, "x")
  if len(xs) < 2 or xs[-2] < 1 or xs[-1] < 1:
    raise ValueError(f"x must have shape [..., L, Dch] with L, Dch >= 1, got {xs}")
  *batch, L, Dch = xs
  if (s := _shape_of(dt, "dt")) != xs:
    raise ValueError(f"dt must have the shape of x {xs}, got {s}")
  As = _shape_of(A, "A")
  if len(As) != 2 or As[0] != Dch or As[1] < 1:
    raise ValueError(f"A must have shape [Dch={Dch}, N], got {As}")
  N = As[1]
  for name, v in (("B", B), ("C", C)):
    if (s := _shape_of(v, name)) != (*batch, L, N):
      raise ValueError(f"{name} must have shape [..., L, N] = {(*batch, L, N)}, got {s}")
  if D is not None and (s := _shape_of(D, "D")) != (Dch,):
    raise ValueError(f"D must have shape [Dch] = {(Dch,)}, got {s}")
  if initial_state is not None and (s := _shape_of(initial_state, "initial_state")) != (
      *batch, Dch, N):
    raise ValueError(f"initial_state must have shape [..., Dch, N] = {(*batch, Dch, N)}, got {s}")
  # Value checks on concrete inputs only (under jit they are tracers and are skipped).
  # Host-side NumPy, so constants closed over inside a jit trace are checked too.
  values = {}
  for n, v in (("x", x), ("dt", dt), ("A", A), ("B", B), ("C", C), ("D", D),
               ("initial_state", initial_state)):
    if v is not None and _is_concrete(v):
      v = np.asarray(v)
      values[n] = v.astype(np.float32) if v.dtype.itemsize < 4 else v
      if not np.all(np.isfinite(values[n])):
        raise ValueError(f"{n} holds NaN or infinite values")
  if "A" in values and np.any(values["A"] > 0):
    raise ValueError("A must be real and non-positive (A <= 0: the state decays by exp(dt A))")
  if "dt" in values and np.any(values["dt"] < 0):
    raise ValueError("dt must be non-negative (apply softplus to the raw projection first)")


def _accum_dtype(*arrays) -> jnp.dtype:
  """float64 when any input is float64 and x64 is on, else float32."""
  if jax.config.jax_enable_x64 and any(
      a is not None and jnp.dtype(a.dtype) == jnp.float64 for a in arrays):
    return jnp.dtype(jnp.float64)
  return jnp.dtype(jnp.float32)


# --------------------------------------------------------------- auto choice
#: Off the CPU, ``"auto"`` takes "associative" up to this many state elements ``Bt * L * Dch * N``
#: and "chunked" above. Measured on one H200 (``benchmarks/results/device.md``): at 1.7e7
#: elements ((64, 512, 32, 16) and (128, 256, 32, 16)) "associative" ran forward+backward
#: 3.3x and 2.0x faster than "chunked"; at 4.0e8 (the paper model's temporal SSM, batch 4)
#: "chunked" ran 1.2x faster than "associative" with a quarter of its memory. The bound
#: lies between the two measured sizes (about their geometric mean).
ASSOCIATIVE_MAX_SIZE = 2 ** 26


def resolve_method(method: str, *, backend: str | None = None, size: int | None = None) -> str:
  """The concrete method ``"auto"`` stands for (other methods pass through).

  Rule (measured in ``benchmarks/results/scan.md``, 2 cores, XLA:CPU): on CPU
  "sequential" at every shape. At the benchmark's shapes ``(64, 512, 32, 16)`` and
  ``(128, 256, 32, 16)`` it was the fastest method forward (1.2-1.7x the exp
  floor, against 2.2-2.8x for "blockwise", 4.8-5.9x "chunked", 14-19x
  "associative") and forward+backward (13-15x, against 14-18x for "blockwise"
  and "chunked"), with the least memory; the earlier shapes ``(256, 512, 32, 16)``,
  ``(64, 128, 16, 16)``, ``(512, 256, 32, 16)`` ranked the same. The per-step cost
  of ``lax.scan`` on CPU is a few microseconds, small next to the
  ``Bt * Dch * N`` exponentials of a step. Elsewhere (GPU/TPU) "associative" for scans
  of at most :data:`ASSOCIATIVE_MAX_SIZE` state elements, where its log-depth tree
  beats a serial loop, and "chunked" above (parallel inside chunks, memory bounded by
  one chunk, a short serial loop over chunks) or when the size is not given.

  Args:
    method: one of :data:`METHODS`.
    backend: ``jax.default_backend()`` when None.
    size: the scan's state elements ``Bt * L * Dch * N`` (None: unknown).
  Raises ValueError for an unknown method or a negative size.
  """
  if method not in METHODS:
    raise ValueError(f"unknown scan method {method!r}; choose one of {METHODS}")
  if size is not None and int(size) < 0:
    raise ValueError(f"size (the scan's state elements) must be >= 0, got {size}")
  if method != "auto":
    return method
  backend = backend or jax.default_backend()
  if backend == "cpu":
    return "sequential"
  return "associative" if size is not None and size <= ASSOCIATIVE_MAX_SIZE else "chunked"


# -------------------------------------------------------------------- kernels
def _combine(left, right):
  """Compose two affine maps ``h -> a h + b``: first ``left``, then ``right``."""
  a_l, b_l = left
  a_r, b_r = right
  return a_r * a_l, a_r * b_l + b_r


# Internally the state is laid out [..., N, Dch] (channels minor) and A is
# passed transposed, At = A.T [N, Dch]: the contraction over N is then a sum of
# whole channel vectors, which XLA:CPU vectorises (2x faster than N minor).
def _discretize(x, dt, At, B):
  """``a = exp(dt A)``, ``b = dt x B``, ``[..., N, Dch]`` each.

  ``x, dt`` ``[..., Dch]``; ``At`` ``[N, Dch]``; ``B`` ``[..., N]``.
  """
  a = jnp.exp(dt[..., None, :] * At)
  b = (dt * x)[..., None, :] * B[..., :, None]
  return a, b


def _contract(h, C):
  """``y[..., d] = sum_n h[..., n, d] C[..., n]``."""
  return _sum_n(h, C)


# The reductions of a step are written as contractions (dot_general), not as
# multiply-then-sum: XLA:CPU runs a [Bt, N, Dch] reduction over N or Dch as a
# slow, poorly vectorised loop, and the batched matrix-vector product fast
# (measured at (64, 512, 32, 16): the adjoint step's reductions 1.5x faster).
def _sum_n(v, w):
  """``out[..., d] = sum_n v[..., n, d] w[..., n]`` for ``v`` ``[..., N, Dch]``, ``w`` ``[..., N]``."""
  return jnp.einsum("...nd,...n->...d", v, w, precision="highest")


def _sum_d(v, w):
  """``out[..., n] = sum_d v[..., n, d] w[..., d]`` for ``v`` ``[..., N, Dch]``, ``w`` ``[..., Dch]``."""
  return jnp.einsum("...nd,...d->...n", v, w, precision="highest")


def _seq_forward(At, h0, x, dt, B, C, reverse, unroll):
  """Fused ``lax.scan``; time-major ``x, dt`` ``[K, Bt, Dch]``, ``B, C`` ``[K, Bt, N]``.

  Returns ``(h_last [Bt, N, Dch], y [K, Bt, Dch])``.
  """
  def step(h, inp):
    x_t, dt_t, B_t, C_t = inp
    a, b = _discretize(x_t, dt_t, At, B_t)
    h = a * h + b
    return h, _contract(h, C_t)
  return lax.scan(step, h0, (x, dt, B, C), reverse=reverse, unroll=unroll)


def _assoc_states(At, h0, x, dt, B, reverse):
  """Decays ``a`` and all states ``h``, ``[K, Bt, N, Dch]``, by ``lax.associative_scan``."""
  a, b = _discretize(x, dt, At, B)
  first = -1 if reverse else 0
  b = b.at[first].add(a[first] * h0)
  return a, lax.associative_scan(_combine, (a, b), axis=0, reverse=reverse)[1]


def _assoc_forward(At, h0, x, dt, B, C, reverse):
  _, h = _assoc_states(At, h0, x, dt, B, reverse)
  return h[0 if reverse else -1], _contract(h, C)


def _chunk(v, K):
  """Time-major ``[L, ...]`` -> ``[ceil(L / K), K, ...]``, zero-padded at the end.

  Zero ``dt`` and ``x`` make padded steps the identity (``a = 1``, ``b = 0``),
  so the padding changes no state in either direction.
  """
  L = v.shape[0]
  pad = -L % K
  if pad:
    v = jnp.pad(v, [(0, pad)] + [(0, 0)] * (v.ndim - 1))
  return v.reshape((v.shape[0] // K, K) + v.shape[1:])


def _unchunk(v, L):
  return v.reshape((-1,) + v.shape[2:])[:L]


def _chunked_forward(At, h0, x, dt, B, C, reverse, K, inner, unroll, keep_states):
  """Outer ``lax.scan`` over chunks carrying the state; ``inner`` scans each chunk.

  Returns ``(h_last, y [L, Bt, Dch], h_in [ceil(L / K), Bt, N, Dch] or None)``:
  ``h_in`` holds the state entering each chunk (in the scan's direction).
  """
  L = x.shape[0]
  def body(h, inp):
    xc, dtc, Bc, Cc = inp
    if inner == "sequential":
      h_new, yc = _seq_forward(At, h, xc, dtc, Bc, Cc, reverse, unroll)
    else:
      h_new, yc = _assoc_forward(At, h, xc, dtc, Bc, Cc, reverse)
    return h_new, ((yc, h) if keep_states else yc)
  chunks = tuple(_chunk(v, K) for v in (x, dt, B, C))
  h_last, out = lax.scan(body, h0, chunks, reverse=reverse)
  y, h_in = out if keep_states else (out, None)
  return h_last, _unchunk(y, L), h_in


# ------------------------------------------------------------------- backward
# With g_t = dL/dh_t (total) and G_t = a_t g_t = dL/dh_{t-1} through h_t:
#   g_t = C_t gy_t + G_{t+1}          (G_{L+1} = cotangent of the final state)
#   dL/dx_t  = dt_t sum_n g_t B_t               dL/dB_t = sum_d g_t dt_t x_t
#   dL/ddt_t = x_t sum_n g_t B_t + sum_n A g_t h_{t-1} a_t
#   dL/dA    = sum_t dt_t g_t h_{t-1} a_t       dL/dC_t = sum_d gy_t h_t
#   dL/dh_0  = G_1
# (for reverse=True swap t-1 and t+1).
def _grads(At, x, dt, B, gy, h, h_prev, a, g):
  """Cotangents of one step (or a block of steps) from the adjoint ``g`` ``[..., N, Dch]``."""
  gla = g * h_prev * a                               # dL/d(dt A)
  s = _sum_n(g, B)                                   # [..., Dch]
  return ((dt * s,                                   # gx
           x * s + jnp.sum(gla * At, axis=-2),       # gdt
           _sum_d(g, dt * x),                        # gB
           _sum_d(h, gy)),                           # gC
          gla * dt[..., None, :])                    # gA terms


def _seq_chunk_backward(At, h_in, G, x, dt, B, C, gy, reverse, unroll):
  """One chunk's cotangents by two fused scans (states, then the adjoint).

  Args:
    h_in: ``[Bt, N, Dch]`` state entering the chunk.
    G: ``[Bt, N, Dch]`` cotangent of the state leaving the chunk.
    x, dt, gy: ``[K, Bt, Dch]``; B, C: ``[K, Bt, N]`` (time-major).

  Returns ``(G_in, gAt [N, Dch], (gx, gdt, gB, gC))``.
  """
  def state_step(h, inp):
    x_t, dt_t, B_t = inp
    a, b = _discretize(x_t, dt_t, At, B_t)
    return a * h + b, h
  _, h_prev = lax.scan(state_step, h_in, (x, dt, B), reverse=reverse, unroll=unroll)

  def adjoint_step(carry, inp):
    G, gA = carry
    x_t, dt_t, B_t, C_t, gy_t, hp = inp
    a, b = _discretize(x_t, dt_t, At, B_t)
    h = a * hp + b
    g = gy_t[..., None, :] * C_t[..., :, None] + G
    grads, gA_t = _grads(At, x_t, dt_t, B_t, gy_t, h, hp, a, g)
    return (a * g, gA + gA_t), grads
  (G_in, gA), grads = lax.scan(adjoint_step, (G, jnp.zeros_like(G)),
                               (x, dt, B, C, gy, h_prev), reverse=not reverse, unroll=unroll)
  return G_in, jnp.sum(gA, axis=0), grads


def _assoc_chunk_backward(At, h_in, G, x, dt, B, C, gy, reverse):
  """As :func:`_seq_chunk_backward`, with associative scans for states and adjoint."""
  a, h = _assoc_states(At, h_in, x, dt, B, reverse)
  ones = jnp.ones_like(a[:1])
  if reverse:    # h_t = a_t h_{t+1} + b_t;  g_t = C_t gy_t + a_{t-1} g_{t-1}
    h_prev = jnp.concatenate([h[1:], h_in[None]])
    a_next = jnp.concatenate([ones, a[:-1]])
    first, last = -1, 0
  else:          # h_t = a_t h_{t-1} + b_t;  g_t = C_t gy_t + a_{t+1} g_{t+1}
    h_prev = jnp.concatenate([h_in[None], h[:-1]])
    a_next = jnp.concatenate([a[1:], ones])
    first, last = 0, -1
  c = gy[..., None, :] * C[..., :, None]
  c = c.at[last].add(G)
  g = lax.associative_scan(_combine, (a_next, c), axis=0, reverse=not reverse)[1]
  grads, gA = _grads(At, x, dt, B, gy, h, h_prev, a, g)
  return a[first] * g[first], jnp.sum(gA, axis=(0, 1)), grads


# ------------------------------------------------------------------ blockwise
# "blockwise": time in blocks of K steps, all blocks at once. Pass 1 computes each block's
# affine summary h_out = P h_in + S from a zero state (P = exp(A sum dt) in closed form,
# S by a fused scan over the K steps, batched over blocks); an associative scan over the
# nb = L / K summaries gives the state entering every block (log depth across blocks);
# pass 2 reruns each block from its entering state, contracting with C as it goes. Only
# states [nb, Bt, N, Dch] and one step's a, b live at a time: nothing [L, ..., N, Dch].
def _to_blocks(v, K):
  """Time-major ``[L, ...]`` -> ``[K, nb, ...]`` (zero-padded: padded steps are the identity)."""
  return jnp.swapaxes(_chunk(v, K), 0, 1)


def _from_blocks(v, L):
  """``[K, nb, ...]`` -> ``[L, ...]``."""
  return _unchunk(jnp.swapaxes(v, 0, 1), L)


def _block_decay(At, dt, reverse):
  """``P = prod_k exp(dt_k A) = exp(A sum_k dt_k)`` per block, ``[nb, Bt, N, Dch]``."""
  del reverse                                        # a product: the same either way
  return jnp.exp(jnp.sum(dt, axis=0)[..., None, :] * At)


def _entering(P, S, h0, reverse):
  """``(entering [nb, ...], last)``: the state entering each block and the final state.

  Blocks compose as ``h_out = P h_in + S`` in the scan's direction; ``h0`` enters the
  first block.
  """
  first = -1 if reverse else 0
  S = S.at[first].add(P[first] * h0)
  leaving = lax.associative_scan(_combine, (P, S), axis=0, reverse=reverse)[1]
  if reverse:
    return jnp.concatenate([leaving[1:], h0[None]]), leaving[0]
  return jnp.concatenate([h0[None], leaving[:-1]]), leaving[-1]


def _blockwise_forward(At, h0, x, dt, B, C, reverse, K, unroll):
  """Returns ``(h_last, y [L, Bt, Dch], entering [nb, Bt, N, Dch])``."""
  L = x.shape[0]
  xb, dtb, Bb, Cb = (_to_blocks(v, K) for v in (x, dt, B, C))

  def summary_step(S, inp):
    x_t, dt_t, B_t = inp
    a, b = _discretize(x_t, dt_t, At, B_t)
    return a * S + b, None
  zero = jnp.zeros(xb.shape[1:-1] + At.shape, h0.dtype)           # [nb, Bt, N, Dch]
  S, _ = lax.scan(summary_step, zero, (xb, dtb, Bb), reverse=reverse, unroll=unroll)
  entering, h_last = _entering(_block_decay(At, dtb, reverse), S, h0, reverse)
  _, y = _seq_forward(At, entering, xb, dtb, Bb, Cb, reverse, unroll)
  return h_last, _from_blocks(y, L), entering


def _blockwise_backward(At, entering, g_last, x, dt, B, C, gy, reverse, K, unroll):
  """Cotangents with the forward's block structure.

  The adjoint runs against the scan's direction: each block maps the cotangent of the
  state leaving it, ``G_out``, to that of the state entering it, ``G_in = P G_out + Q``
  (``Q``: the block's own ``C gy`` terms carried back from a zero cotangent). A reverse
  associative scan over the blocks' ``(P, Q)`` gives every ``G_out``; then each block's
  states and adjoint are recomputed and its cotangents formed step by step
  (:func:`_seq_chunk_backward`), one block at a time so that no more than one block's
  ``[K, Bt, N, Dch]`` states are alive.
  """
  L = x.shape[0]
  chunks = tuple(_chunk(v, K) for v in (x, dt, B, C, gy))          # [nb, K, ...]
  xb, dtb, Bb, Cb, gyb = (jnp.swapaxes(v, 0, 1) for v in chunks)    # [K, nb, ...]

  def adjoint_summary_step(G, inp):
    x_t, dt_t, B_t, C_t, gy_t = inp
    a, _ = _discretize(x_t, dt_t, At, B_t)
    return a * (gy_t[..., None, :] * C_t[..., :, None] + G), None
  Q, _ = lax.scan(adjoint_summary_step, jnp.zeros_like(entering), (xb, dtb, Bb, Cb, gyb),
                  reverse=not reverse, unroll=unroll)
  G_out, _ = _entering(_block_decay(At, dtb, reverse), Q, g_last, not reverse)

  def one_block(inp):
    h_in, G, *steps = inp
    return _seq_chunk_backward(At, h_in, G, *steps, reverse, unroll)
  # One block at a time: its states and adjoint, [K, Bt, N, Dch], are the largest
  # transients (all blocks at once held [L, Bt, N, Dch]: 111 MB at (64, 512, 32, 16)).
  G_in, gAt, grads = lax.map(one_block, (entering, G_out) + chunks)
  gh0 = G_in[-1] if reverse else G_in[0]
  gx, gdt, gB, gC = (_unchunk(v, L) for v in grads)
  return gh0, jnp.sum(gAt, axis=0), (gx, gdt, gB, gC)


# ------------------------------------------------------------------ custom VJP
@functools.partial(jax.custom_vjp, nondiff_argnums=(6, 7, 8, 9))
def _ssm(x, dt, At, B, C, h0, method, reverse, chunk, unroll):
  """Time-major core: ``x, dt`` ``[L, Bt, Dch]``, ``At`` ``[N, Dch]``, ``B, C`` ``[L, Bt, N]``,
  ``h0`` ``[Bt, N, Dch]``.

  Returns ``(y [L, Bt, Dch] without the D term, h_last [Bt, N, Dch])``.
  """
  if method == "sequential":
    h_last, y = _seq_forward(At, h0, x, dt, B, C, reverse, unroll)
  elif method == "associative":
    h_last, y = _assoc_forward(At, h0, x, dt, B, C, reverse)
  elif method == "blockwise":
    h_last, y, _ = _blockwise_forward(At, h0, x, dt, B, C, reverse, chunk, unroll)
  else:
    h_last, y, _ = _chunked_forward(At, h0, x, dt, B, C, reverse, chunk, "associative",
                                    unroll, keep_states=False)
  return y, h_last


def _ssm_fwd(x, dt, At, B, C, h0, method, reverse, chunk, unroll):
  if method == "associative":
    h_last, y = _assoc_forward(At, h0, x, dt, B, C, reverse)
    h_in = None
  elif method == "blockwise":
    h_last, y, h_in = _blockwise_forward(At, h0, x, dt, B, C, reverse, chunk, unroll)
  else:
    inner = "sequential" if method == "sequential" else "associative"
    h_last, y, h_in = _chunked_forward(At, h0, x, dt, B, C, reverse, chunk, inner, unroll,
                                       keep_states=True)
  return (y, h_last), (x, dt, At, B, C, h0, h_in)


def _ssm_bwd(method, reverse, chunk, unroll, res, cts):
  x, dt, At, B, C, h0, h_in = res
  gy, g_last = cts
  if method == "associative":
    gh0, gAt, (gx, gdt, gB, gC) = _assoc_chunk_backward(At, h0, g_last, x, dt, B, C, gy, reverse)
    return gx, gdt, gAt, gB, gC, gh0
  if method == "blockwise":
    gh0, gAt, (gx, gdt, gB, gC) = _blockwise_backward(At, h_in, g_last, x, dt, B, C, gy, reverse,
                                                      chunk, unroll)
    return gx, gdt, gAt, gB, gC, gh0
  L = x.shape[0]

  def body(carry, inp):
    G, gAt = carry
    xc, dtc, Bc, Cc, gyc, hc = inp
    if method == "sequential":
      G, gAc, grads = _seq_chunk_backward(At, hc, G, xc, dtc, Bc, Cc, gyc, reverse, unroll)
    else:
      G, gAc, grads = _assoc_chunk_backward(At, hc, G, xc, dtc, Bc, Cc, gyc, reverse)
    return (G, gAt + gAc), grads
  chunks = tuple(_chunk(v, chunk) for v in (x, dt, B, C, gy)) + (h_in,)
  (gh0, gAt), grads = lax.scan(body, (g_last, jnp.zeros_like(At)), chunks, reverse=not reverse)
  gx, gdt, gB, gC = (_unchunk(v, L) for v in grads)
  return gx, gdt, gAt, gB, gC, gh0


_ssm.defvjp(_ssm_fwd, _ssm_bwd)


# ------------------------------------------------------------------ public API
def selective_scan(x, dt, A, B, C, D=None, *, reverse: bool = False, method: str = "auto",
                   initial_state=None, return_state: bool = False, chunk_size: int | None = None,
                   unroll: int = 1):
  """Mamba v1 selective scan ``y_t = <C_t, h_t> + D x_t``, ``h_t = exp(dt_t A) h_{t-1} + dt_t B_t x_t``.

  Pure and jit-compatible; the leading ``...`` axes are a batch.

  Args:
    x: ``[..., L, Dch]`` input sequence (any float dtype).
    dt: ``[..., L, Dch]`` step sizes ``Delta > 0`` (already through softplus), in
      units of the time constants ``1 / |A|``.
    A: ``[Dch, N]`` state matrix diagonal, ``<= 0`` (Mamba: ``-exp(A_log)``).
    B: ``[..., L, N]`` input projection, shared by all channels.
    C: ``[..., L, N]`` output projection, shared by all channels.
    D: ``[Dch]`` skip weight, or None for no skip term.
    reverse: scan from the last step to the first (anti-causal): ``h_t``
      depends on ``h_{t+1}`` and ``initial_state`` enters at step ``L``.
    method: "auto" (default: the fastest measured kernel, :func:`resolve_method`) |
      "sequential" | "blockwise" | "chunked" | "associative" (see the module docstring).
      All give the same result up to rounding.
    initial_state: ``[..., Dch, N]`` state before the first step (in the scan's
      direction), zeros when None.
    return_state: also return the state after the last step.
    chunk_size: steps per chunk for "chunked" (the scan unit), per block for
      "blockwise", and for "sequential" (how often the forward pass of a
      differentiated call keeps the state for the backward pass); default
      :data:`DEFAULT_CHUNK` (64, "chunked" 8). Ignored by "associative".
    unroll: ``lax.scan`` unroll factor of the sequential steps.

  Returns:
    ``y`` ``[..., L, Dch]`` in the dtype of ``x``; with ``return_state`` the pair
    ``(y, h_last)``, ``h_last`` ``[..., Dch, N]`` in float32 (float64 for float64
    inputs under x64).

  Raises:
    ValueError: naming the argument, for a wrong shape or dtype, an unknown method,
      and (outside jit) NaN/inf values, ``A > 0`` or ``dt < 0``.

  Example:
    >>> import jax.numpy as jnp
    >>> from nlosjax.ssm import selective_scan
    >>> x = jnp.ones((2, 8, 4)); dt = jnp.full((2, 8, 4), 0.1)
    >>> A = -jnp.tile(jnp.arange(1.0, 3.0), (4, 1)); B = C = jnp.ones((2, 8, 2))
    >>> selective_scan(x, dt, A, B, C).shape
    (2, 8, 4)

  References:
    Gu & Dao, "Mamba: Linear-Time Sequence Modeling with Selective State Spaces",
    https://arxiv.org/abs/2312.00752 (Alg. 2, Sec. 3.3).
  """
  x, dt, A, B, C = (jnp.asarray(v) for v in (x, dt, A, B, C))
  D = None if D is None else jnp.asarray(D)
  initial_state = None if initial_state is None else jnp.asarray(initial_state)
  _check_inputs(x, dt, A, B, C, D, initial_state, method, chunk_size)
  if not (isinstance(unroll, (int, np.integer)) and unroll >= 1) or isinstance(unroll, bool):
    raise ValueError(f"unroll must be a positive integer, got {unroll!r}")
  out_dtype = x.dtype
  acc = _accum_dtype(x, dt, A, B, C, D, initial_state)
  *batch, L, Dch = x.shape
  N = A.shape[1]
  Bt = int(np.prod(batch, dtype=np.int64))
  method = resolve_method(method, size=Bt * L * Dch * N)
  chunk = int(chunk_size or DEFAULT_CHUNK.get(method, L))
  chunk = min(chunk, L)

  def time_major(v):
    v = v.astype(acc).reshape((Bt, L, v.shape[-1]))
    return jnp.swapaxes(v, 0, 1)
  h0 = (jnp.zeros((Bt, N, Dch), acc) if initial_state is None else jnp.swapaxes(
      initial_state.astype(acc).reshape((Bt, Dch, N)), 1, 2))
  y, h_last = _ssm(time_major(x), time_major(dt), A.astype(acc).T, time_major(B), time_major(C),
                   h0, method, bool(reverse), chunk, int(unroll))
  y = jnp.swapaxes(y, 0, 1).reshape((*batch, L, Dch))
  if D is not None:
    y = y + D.astype(acc) * x.astype(acc)
  y = y.astype(out_dtype)
  if return_state:
    return y, jnp.swapaxes(h_last, 1, 2).reshape((*batch, Dch, N))
  return y


def bidirectional_scan(x, dt, A, B, C, D=None, *, reverse_inputs: Mapping | None = None,
                       combine: str = "mean", method: str = "auto",
                       chunk_size: int | None = None, unroll: int = 1):
  """Forward (causal) plus reverse (anti-causal) selective scans of one sequence (Vision Mamba).

  ``y = combine(selective_scan(x, dt, A, B, C, D), selective_scan(x', dt', A', B', C', D',
  reverse=True))`` where the primed inputs are ``reverse_inputs`` entries and default
  to the forward ones. Every output step sees the whole sequence. The reverse pass
  runs on the original order (no flipped copies); it equals Vim's causal pass over
  the flipped sequence, flipped back.

  Parameter sharing is the caller's choice: Vim ``bimamba_type="v2"`` passes
  separate ``x`` (its own conv), ``dt``, ``A``, ``B``, ``C`` and ``D`` for the
  reverse pass; ``"v1"`` passes only a separate ``A``; with ``reverse_inputs=None``
  both passes share everything.

  Args:
    x, dt: ``[..., L, Dch]``; A: ``[Dch, N]``; B, C: ``[..., L, N]``; D: ``[Dch]`` or
      None -- the forward pass, as in :func:`selective_scan`.
    reverse_inputs: optional mapping with any of the keys ``"x", "dt", "A", "B",
      "C", "D"`` (same shapes) overriding the forward inputs for the reverse pass.
    combine: "mean" (``(y_f + y_r) / 2``, Vim's ``if_divide_out`` default, which keeps
      magnitudes layer to layer), "sum", or "none" to return the pair ``(y_f, y_r)``.
    method, chunk_size, unroll: as in :func:`selective_scan`, for both passes.

  Returns:
    ``y`` ``[..., L, Dch]`` in the dtype of ``x`` (a pair for ``combine="none"``).
  """
  if combine not in COMBINES:
    raise ValueError(f"combine must be one of {COMBINES}, got {combine!r}")
  rev = dict(reverse_inputs or {})
  unknown = set(rev) - {"x", "dt", "A", "B", "C", "D"}
  if unknown:
    raise ValueError(f"reverse_inputs keys must be among x, dt, A, B, C, D; got {sorted(unknown)}")
  kw = dict(method=method, chunk_size=chunk_size, unroll=unroll)
  y_f = selective_scan(x, dt, A, B, C, D, **kw)
  fwd = dict(x=x, dt=dt, A=A, B=B, C=C, D=D)
  fwd.update(rev)
  y_r = selective_scan(fwd["x"], fwd["dt"], fwd["A"], fwd["B"], fwd["C"], fwd["D"],
                       reverse=True, **kw)
  if combine == "none":
    return y_f, y_r
  acc = jnp.promote_types(y_f.dtype, jnp.float32)
  y = y_f.astype(acc) + y_r.astype(acc)
  if combine == "mean":
    y = 0.5 * y
  return y.astype(y_f.dtype)
