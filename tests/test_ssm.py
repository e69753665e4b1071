"""Selective scan and Mamba mixer: exactness, gradients, causality, stability, errors, init.

Independent references:

* ``naive_scan``: the recurrence as a plain Python loop over time in NumPy float64.
* ``naive_scan_vjp``: that loop's adjoint (gradients of a weighted sum), NumPy float64.
* ``naive_scan_jax``: the same loop in ``jax.numpy`` (no ``lax.scan``, no custom VJP), whose
  plain autodiff gives reference gradients in float64.
* ``selective_scan_ref_np``: a NumPy port, written for these tests, of the semantics of
  mamba_ssm's ``selective_scan_ref`` (state-spaces/mamba, ``ops/selective_scan_interface.py``):
  channels-first layout ``u, delta`` ``[B, D, L]``, ``B, C`` ``[B, N, L]``, fp32 upcast,
  ``delta_bias`` and PyTorch's thresholded softplus applied inside, the discretisation
  materialised as ``deltaA [B, D, L, N]`` / ``deltaB_u`` by einsum, the state loop, ``D`` skip,
  SiLU(z) gate, cast back. It is the "established implementation" the kernels are
  checked against (PyTorch is not a dependency of this project).
* ``mixer_ref_np``: a NumPy Mamba v1 / Vim-v2 mixer forward built on that port, with the
  causal conv written as PyTorch's padded cross-correlation.
"""

import math

import flax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from nlosjax.ssm import MambaMixer, bidirectional_scan, resolve_method, selective_scan
from nlosjax.ssm import scan as scan_module
from nlosjax.ssm.mamba import depthwise_conv

# Every kernel of the library ("auto" resolves to one of them), the sequential reference first.
METHODS = ("sequential", *(m for m in scan_module.METHODS if m not in ("sequential", "auto")))
# Every call under jit: op-by-op (eager) dispatch of the scans is what makes tests slow.
scan = jax.jit(selective_scan, static_argnames=("reverse", "method", "return_state",
                                                "chunk_size", "unroll"))
CHUNK = 5  # small and not a divisor of the test lengths, so padding is exercised


# ------------------------------------------------------------------ references
def naive_scan(x, dt, A, B, C, D=None, h0=None, reverse=False):
  """Plain loop, NumPy float64. x, dt [Bt, L, Dch]; A [Dch, N]; B, C [Bt, L, N]."""
  x, dt, A, B, C = (np.asarray(v, np.float64) for v in (x, dt, A, B, C))
  Bt, L, Dch = x.shape
  h = np.zeros((Bt, Dch, A.shape[1])) if h0 is None else np.array(h0, np.float64)
  y = np.zeros_like(x)
  for t in (range(L - 1, -1, -1) if reverse else range(L)):
    for b in range(Bt):
      for d in range(Dch):
        h[b, d] = np.exp(dt[b, t, d] * A[d]) * h[b, d] + dt[b, t, d] * x[b, t, d] * B[b, t]
        y[b, t, d] = h[b, d] @ C[b, t]
  if D is not None:
    y = y + np.asarray(D, np.float64) * x
  return y, h


def naive_scan_vjp(x, dt, A, B, C, w):
  """Gradients of ``sum(w * y)`` (``y`` of :func:`naive_scan`, no ``D``, ``h0 = 0``, causal)
  wrt ``x, dt, B, C``: the adjoint recurrence ``lam_t = w_t C_t + exp(dt_{t+1} A) lam_{t+1}``
  as a NumPy float64 loop."""
  x, dt, A, B, C, w = (np.asarray(v, np.float64) for v in (x, dt, A, B, C, w))
  Bt, L, Dch = x.shape
  h = np.zeros((Bt, L + 1, Dch, A.shape[1]))            # h[:, t + 1] is the state after step t
  decay = np.exp(dt[..., None] * A)                      # [Bt, L, Dch, N]
  for t in range(L):
    h[:, t + 1] = decay[:, t] * h[:, t] + (dt[:, t] * x[:, t])[..., None] * B[:, t, None, :]
  gx, gdt, gB, gC = (np.zeros_like(v) for v in (x, dt, B, C))
  lam = np.zeros((Bt, Dch, A.shape[1]))
  for t in range(L - 1, -1, -1):
    lam = w[:, t, :, None] * C[:, t, None, :] + (decay[:, t + 1] * lam if t + 1 < L else 0.0)
    gC[:, t] = np.einsum("bd,bdn->bn", w[:, t], h[:, t + 1])
    gx[:, t] = dt[:, t] * np.einsum("bdn,bn->bd", lam, B[:, t])
    gB[:, t] = np.einsum("bdn,bd->bn", lam, dt[:, t] * x[:, t])
    gdt[:, t] = np.sum(lam * (A * decay[:, t] * h[:, t] + x[:, t, :, None] * B[:, t, None, :]), -1)
  return gx, gdt, gB, gC


def naive_scan_jax(x, dt, A, B, C, D, h0, reverse):
  """The same loop in jnp (unrolled over L): plain autodiff gives reference gradients."""
  L = x.shape[1]
  h = h0
  ys = [None] * L
  for t in (range(L - 1, -1, -1) if reverse else range(L)):
    h = jnp.exp(dt[:, t, :, None] * A) * h + (dt[:, t] * x[:, t])[:, :, None] * B[:, t, None, :]
    ys[t] = jnp.sum(h * C[:, t, None, :], axis=-1)
  return jnp.stack(ys, axis=1) + D * x, h


def _torch_softplus(v):
  """PyTorch ``F.softplus`` (beta 1, threshold 20)."""
  return np.where(v > 20.0, v, np.log1p(np.exp(np.minimum(v, 20.0))))


def _silu(v):
  return v / (1.0 + np.exp(-v))


def selective_scan_ref_np(u, delta, A, B, C, D=None, z=None, delta_bias=None,
                          delta_softplus=False, return_last_state=False):
  """NumPy port of mamba_ssm ``selective_scan_ref`` (real, variable B/C of shape [B, N, L]).

  u, delta, z: [B, D, L]; A: [D, N]; B, C: [B, N, L]; D, delta_bias: [D]. Out [B, D, L].
  """
  dtype_in = u.dtype
  u = u.astype(np.float64 if dtype_in == np.float64 else np.float32)
  work = u.dtype
  delta = delta.astype(work)
  if delta_bias is not None:
    delta = delta + delta_bias[..., None].astype(work)
  if delta_softplus:
    delta = _torch_softplus(delta)
  batch, dim, dstate = u.shape[0], A.shape[0], A.shape[1]
  B, C = B.astype(work), C.astype(work)
  x = np.zeros((batch, dim, dstate), work)
  delta_a = np.exp(np.einsum("bdl,dn->bdln", delta, A.astype(work)))
  delta_b_u = np.einsum("bdl,bnl,bdl->bdln", delta, B, u)
  ys = []
  for i in range(u.shape[2]):
    x = delta_a[:, :, i] * x + delta_b_u[:, :, i]
    ys.append(np.einsum("bdn,bn->bd", x, C[:, :, i]))
  y = np.stack(ys, axis=2)
  out = y if D is None else y + u * D[:, None].astype(work)
  if z is not None:
    out = out * _silu(z.astype(work))
  out = out.astype(dtype_in)
  return (out, x) if return_last_state else out


def _torch_causal_conv(x, kernel, bias):
  """``F.conv1d(x, w, b, padding=K-1, groups=D)[..., :L]`` on x [B, D, L]; kernel [K, D]."""
  K, L = kernel.shape[0], x.shape[-1]
  xp = np.pad(x, [(0, 0), (0, 0), (K - 1, K - 1)])
  out = np.zeros(x.shape[:2] + (L + K - 1,))
  for t in range(L + K - 1):
    out[:, :, t] = np.einsum("bdk,kd->bd", xp[:, :, t:t + K], kernel)
  return out[..., :L] + (0.0 if bias is None else bias[None, :, None])


def mixer_ref_np(params, u, *, d_state, bidirectional=False):
  """NumPy Mamba v1 mixer (Vim v2 when bidirectional) from the Flax params; u [B, L, d_model]."""
  p = jax.tree.map(lambda v: np.asarray(v, np.float64), flax.core.unfreeze(params))
  u = np.asarray(u, np.float64)
  xz = u @ p["in_proj"]["kernel"]
  x, z = np.split(np.swapaxes(xz, 1, 2), 2, axis=1)          # [B, d_inner, L]
  s = p["ssm"]             # the SelectiveSSM: reverse-branch names dt_proj_b_kernel, A_log_b, ...

  def branch(x, z, sfx):
    x = _silu(_torch_causal_conv(x, s["conv_kernel" + sfx], s["conv_bias" + sfx]))
    x_dbl = np.swapaxes(x, 1, 2) @ s["x_proj" + sfx]["kernel"]
    R = s[f"dt_proj{sfx}_kernel"].shape[0]
    delta = np.swapaxes(x_dbl[..., :R] @ s[f"dt_proj{sfx}_kernel"], 1, 2)
    Bm = np.swapaxes(x_dbl[..., R:R + d_state], 1, 2)
    Cm = np.swapaxes(x_dbl[..., R + d_state:], 1, 2)
    return selective_scan_ref_np(x, delta, -np.exp(s["A_log" + sfx]), Bm, Cm, s["D" + sfx], z,
                                 delta_bias=s[f"dt_proj{sfx}_bias"], delta_softplus=True)
  y = branch(x, z, "")
  if bidirectional:
    y = (y + branch(x[..., ::-1], z[..., ::-1], "_b")[..., ::-1]) / 2
  return np.swapaxes(y, 1, 2) @ p["out_proj"]["kernel"]


def random_inputs(rng, Bt=2, L=11, Dch=3, N=4, dtype=np.float32):
  x = rng.normal(size=(Bt, L, Dch))
  dt = np.exp(rng.uniform(np.log(1e-2), np.log(2.0), (Bt, L, Dch)))
  A = -np.exp(rng.uniform(np.log(0.1), np.log(4.0), (Dch, N)))
  B = rng.normal(size=(Bt, L, N))
  C = rng.normal(size=(Bt, L, N))
  D = rng.normal(size=(Dch,))
  h0 = rng.normal(size=(Bt, Dch, N))
  return tuple(v.astype(dtype) for v in (x, dt, A, B, C, D, h0))


def rel_err(a, b):
  a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
  return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


@pytest.fixture
def x64():
  """float64 inside the test only; other test modules keep the float32 default."""
  with jax.enable_x64(True):
    yield


def _scan_and_grads(method, reverse, with_h0):
  """jit of (y, h_last, grads of a linear loss wrt x, dt, A, B, C, D, h0)."""
  def f(x, dt, A, B, C, D, h0, wy, wh):
    y, h = selective_scan(x, dt, A, B, C, D, reverse=reverse, method=method,
                          initial_state=h0 if with_h0 else None, return_state=True,
                          chunk_size=CHUNK)
    return jnp.sum(y * wy) + jnp.sum(jnp.sin(h) * wh), (y, h)
  return jax.jit(jax.value_and_grad(f, argnums=(0, 1, 2, 3, 4, 5, 6), has_aux=True))


# --------------------------------------------------------- exactness, float64
@pytest.mark.parametrize("reverse, with_h0", [(False, True), (True, True)])
def test_every_method_matches_the_naive_loop_in_float64(x64, reverse, with_h0):
  """Forward, final state and all seven gradients; ``initial_state=None`` is covered by the
  port of selective_scan_ref below (and the float32 tests)."""
  rng = np.random.default_rng(1)
  x, dt, A, B, C, D, h0 = random_inputs(rng, dtype=np.float64)
  wy, wh = rng.normal(size=x.shape), rng.normal(size=h0.shape)
  y_ref, h_ref = naive_scan(x, dt, A, B, C, D, h0 if with_h0 else None, reverse)
  # Reference gradients: plain autodiff of the jnp loop (no lax.scan, no custom VJP).
  def ref_loss(x, dt, A, B, C, D, h0):
    y, h = naive_scan_jax(x, dt, A, B, C, D, h0 if with_h0 else jnp.zeros_like(h0), reverse)
    return jnp.sum(y * wy) + jnp.sum(jnp.sin(h) * wh)
  g_ref = jax.jit(jax.grad(ref_loss, argnums=tuple(range(7))))(x, dt, A, B, C, D, h0)
  for method in METHODS:
    (_, (y, h)), grads = _scan_and_grads(method, reverse, with_h0)(x, dt, A, B, C, D, h0, wy, wh)
    assert y.dtype == jnp.float64 and h.dtype == jnp.float64
    np.testing.assert_allclose(y, y_ref, rtol=0, atol=1e-10 * np.abs(y_ref).max(), err_msg=method)
    np.testing.assert_allclose(h, h_ref, rtol=0, atol=1e-10 * np.abs(h_ref).max(), err_msg=method)
    for name, g, gr in zip(("x", "dt", "A", "B", "C", "D", "h0"), grads, g_ref):
      if name == "h0" and not with_h0:
        assert np.all(np.asarray(g) == 0), method
        continue
      assert rel_err(g, gr) < 1e-10, (method, name, rel_err(g, gr))


def test_matches_the_numpy_port_of_mamba_selective_scan_ref(x64):
  """selective_scan(softplus(delta + bias), ...) * silu(z) == selective_scan_ref(..., z, bias)."""
  rng = np.random.default_rng(2)
  Bt, L, Dch, N = 2, 13, 4, 3
  u = rng.normal(size=(Bt, Dch, L))
  delta = rng.normal(size=(Bt, Dch, L)) - 1.0
  bias = rng.normal(size=Dch)
  A = -np.exp(rng.normal(size=(Dch, N)))
  Bm, Cm = rng.normal(size=(Bt, N, L)), rng.normal(size=(Bt, N, L))
  D, z = rng.normal(size=Dch), rng.normal(size=(Bt, Dch, L))
  ref, last = selective_scan_ref_np(u, delta, A, Bm, Cm, D, z, delta_bias=bias,
                                    delta_softplus=True, return_last_state=True)
  t = lambda v: jnp.swapaxes(jnp.asarray(v), 1, 2)   # [B, D, L] -> [B, L, D]
  dt = jax.nn.softplus(t(delta) + bias)
  for method in METHODS:
    y, h = scan(t(u), dt, A, t(Bm), t(Cm), D, method=method, return_state=True)
    out = y * jax.nn.silu(t(z))
    np.testing.assert_allclose(t(out), ref, rtol=1e-10, atol=1e-12, err_msg=method)
    np.testing.assert_allclose(h, last, rtol=1e-10, atol=1e-12, err_msg=method)


# ------------------------------------------------------ agreement, float32
@pytest.mark.parametrize("reverse", [False, True])
def test_methods_agree_in_float32_forward_and_gradients(reverse):
  rng = np.random.default_rng(3)
  x, dt, A, B, C, D, h0 = random_inputs(rng, L=23)
  wy = rng.normal(size=x.shape).astype(np.float32)
  wh = rng.normal(size=h0.shape).astype(np.float32)
  out = {m: _scan_and_grads(m, reverse, True)(x, dt, A, B, C, D, h0, wy, wh) for m in METHODS}
  (_, (y0, h0_)), g0 = out["sequential"]
  assert y0.dtype == jnp.float32
  for m in METHODS[1:]:
    (_, (y, h)), g = out[m]
    assert rel_err(y, y0) < 1e-5 and rel_err(h, h0_) < 1e-5, m
    for a, b in zip(g, g0):
      assert rel_err(a, b) < 1e-5, (m, rel_err(a, b))


def test_reverse_is_the_flipped_causal_scan_and_state_matches_the_loop():
  rng = np.random.default_rng(4)
  x, dt, A, B, C, D, h0 = random_inputs(rng)
  flip = lambda v: v[:, ::-1]
  for m in METHODS:
    y_r, h_r = scan(x, dt, A, B, C, D, reverse=True, method=m, initial_state=h0,
                              return_state=True)
    y_f, h_f = scan(flip(x), flip(dt), A, flip(B), flip(C), D, method=m,
                              initial_state=h0, return_state=True)
    assert rel_err(y_r, flip(y_f)) < 1e-6 and rel_err(h_r, h_f) < 1e-6, m
  _, h_ref = naive_scan(x, dt, A, B, C, None, h0)
  _, h = scan(x, dt, A, B, C, method="sequential", initial_state=h0, return_state=True)
  assert h.shape == (2, 3, 4) and h.dtype == jnp.float32 and rel_err(h, h_ref) < 1e-5


def test_leading_batch_axes_and_no_retrace():
  rng = np.random.default_rng(5)
  x, dt, A, B, C, D, _ = random_inputs(rng, Bt=6)
  traces = []

  def f(x, dt, B, C):
    traces.append(1)
    return selective_scan(x, dt, A, B, C, D, method="sequential")
  f = jax.jit(f)
  r = lambda v: v.reshape((2, 3) + v.shape[1:])
  y = f(x, dt, B, C)
  y6 = f(r(x), r(dt), r(B), r(C))                                # [2, 3, L, Dch]
  y1 = f(x[0], dt[0], B[0], C[0])                                # unbatched [L, Dch]
  assert y6.shape == (2, 3, 11, 3) and y1.shape == (11, 3)
  np.testing.assert_allclose(y6.reshape(y.shape), y, rtol=1e-6, atol=1e-6)
  np.testing.assert_allclose(y1, y[0], rtol=1e-6, atol=1e-6)
  f(x + 1, dt, B, C)
  assert len(traces) == 3                                        # no retrace on new values


# ------------------------------------------------------------------ causality
@pytest.mark.parametrize("method", METHODS)
def test_causal_outputs_before_a_perturbation_are_bit_identical(method):
  rng = np.random.default_rng(6)
  x, dt, A, B, C, D, h0 = random_inputs(rng, L=17)
  t0 = 9
  x2 = x.copy()
  x2[:, t0] += 1.0
  f = jax.jit(lambda x, rev: selective_scan(x, dt, A, B, C, D, method=method, reverse=rev,
                                            initial_state=h0, chunk_size=CHUNK), static_argnums=1)
  y, y2 = np.asarray(f(x, False)), np.asarray(f(x2, False))
  assert np.array_equal(y[:, :t0], y2[:, :t0])
  assert np.all(np.abs(y[:, t0:] - y2[:, t0:]).max(axis=(0, 2)) > 0)
  y, y2 = np.asarray(f(x, True)), np.asarray(f(x2, True))      # anti-causal: the mirror image
  assert np.array_equal(y[:, t0 + 1:], y2[:, t0 + 1:])
  assert np.all(np.abs(y[:, :t0 + 1] - y2[:, :t0 + 1]).max(axis=(0, 2)) > 0)


def test_gradient_is_exactly_causal():
  """d y_t0 / d x_s == 0 exactly for s > t0, through the custom VJP."""
  rng = np.random.default_rng(7)
  x, dt, A, B, C, D, _ = random_inputs(rng, L=9)
  t0 = 4
  w = np.zeros_like(x)
  w[:, t0] = rng.normal(size=w[:, t0].shape)
  for m in METHODS:
    gx, gdt, gB = jax.jit(jax.grad(
        lambda x, dt, B: jnp.sum(selective_scan(x, dt, A, B, C, D, method=m, chunk_size=4) * w),
        argnums=(0, 1, 2)))(x, dt, B)
    for g in (gx, gdt, gB):
      g = np.asarray(g)
      assert np.all(g[:, t0 + 1:] == 0) and np.all(np.abs(g[:, :t0 + 1]).max(axis=(0, 2)) > 0), m


# ----------------------------------------------------------------- stability
def _extreme_inputs(rng, L, Dch=4, N=4):
  """dt log-uniform in [1e-8, 1e4] and A log-uniform in [-1e4, -1e-6], endpoints included."""
  dt = np.exp(rng.uniform(np.log(1e-8), np.log(1e4), (1, L, Dch)))
  dt[0, :2] = [[1e-8], [1e4]]
  A = -np.exp(np.linspace(np.log(1e-6), np.log(1e4), Dch * N)).reshape(Dch, N)
  x = rng.normal(size=(1, L, Dch))
  B, C = rng.normal(size=(1, L, N)), rng.normal(size=(1, L, N))
  return x, dt, A, B, C


def test_extreme_dt_and_A_stay_finite_and_close_to_float64():
  rng = np.random.default_rng(8)
  x, dt, A, B, C = _extreme_inputs(rng, L=40)
  w = rng.normal(size=x.shape)
  with jax.enable_x64(True):
    y64 = scan(*(jnp.asarray(v) for v in (x, dt, A, B, C)), method="sequential")
    g64 = jax.jit(jax.grad(lambda *a: jnp.sum(selective_scan(*a, method="sequential") * w),
                           argnums=(0, 1, 3, 4)))(*(jnp.asarray(v) for v in (x, dt, A, B, C)))
    # The independent references at the same extremes: the NumPy loop (forward) and its
    # adjoint loop (gradients), both NumPy float64.
    y_ref, _ = naive_scan(x, dt, A, B, C)
    g_ref = naive_scan_vjp(x, dt, A, B, C, w)
  assert rel_err(y64, y_ref) < 1e-12, rel_err(y64, y_ref)        # measured 3.7e-16, 9.3e-16
  for a, b in zip(g64, g_ref):
    assert rel_err(a, b) < 1e-10, rel_err(a, b)
  f32 = lambda v: np.asarray(v, np.float32)
  for m in METHODS:
    args = tuple(map(f32, (x, dt, A, B, C)))
    y = scan(*args, method=m, chunk_size=8)
    g = jax.jit(jax.grad(lambda *a: jnp.sum(selective_scan(*a, method=m, chunk_size=8) * f32(w)),
                         argnums=(0, 1, 2, 3, 4)))(*args)
    assert np.all(np.isfinite(y)) and all(np.all(np.isfinite(v)) for v in g), m
    assert rel_err(y, y64) < 1e-4, (m, rel_err(y, y64))
    # Measured against the references: forward <= 1.7e-7, gradients <= 1.8e-7 (float32 round-off).
    assert rel_err(y, y_ref) < 1e-6, (m, rel_err(y, y_ref))
    for a, b, r in zip((g[0], g[1], g[3], g[4]), g64, g_ref):
      assert rel_err(a, b) < 1e-3, (m, rel_err(a, b))
      assert rel_err(a, r) < 1e-6, (m, rel_err(a, r))


def test_long_sequence_16384_steps():
  rng = np.random.default_rng(9)
  L = 16384
  x, dt, A, B, C = _extreme_inputs(rng, L, Dch=2, N=2)
  dt = np.clip(dt, 1e-3, 1.0)     # a slowly forgetting state across the whole sequence
  A = -np.array([[1e-6, 1e-3], [1e-2, 1.0]])
  with jax.enable_x64(True):
    y64 = scan(*(jnp.asarray(v) for v in (x, dt, A, B, C)), method="sequential")
  for m in METHODS:
    args = tuple(np.asarray(v, np.float32) for v in (x, dt, A, B, C))
    y, g = jax.jit(jax.value_and_grad(
        lambda x, dt: jnp.sum(selective_scan(x, dt, *args[2:], method=m)), argnums=(0, 1)))(
            *args[:2])
    assert np.isfinite(y) and all(np.all(np.isfinite(v)) for v in g), m
    y = scan(*args, method=m)
    assert rel_err(y, y64) < 1e-3, (m, rel_err(y, y64))


def test_zero_and_very_large_inputs():
  rng = np.random.default_rng(10)
  x, dt, A, B, C, D, _ = random_inputs(rng)
  zero = lambda v: np.zeros_like(v)
  big = x * np.float32(1e15)
  y_ref, _ = naive_scan(big, dt, A, B, C, D)
  for m in METHODS:
    vg = jax.jit(jax.value_and_grad(
        lambda x, dt, B, C: jnp.sum(selective_scan(x, dt, A, B, C, D, method=m)), argnums=(0, 1, 2, 3)))
    y = scan(zero(x), zero(dt), A, zero(B), zero(C), D, method=m)
    assert np.all(np.asarray(y) == 0), m
    v, g = vg(zero(x), zero(dt), zero(B), zero(C))
    assert v == 0 and all(np.all(np.isfinite(t)) for t in g), m
    y = scan(big, dt, A, B, C, D, method=m)
    assert np.all(np.isfinite(y)) and rel_err(y, y_ref) < 1e-5, m
    v, g = vg(big, dt, B, C)
    assert np.isfinite(v) and all(np.all(np.isfinite(t)) for t in g), m


@pytest.mark.parametrize("dtype, methods", [(jnp.bfloat16, METHODS), (jnp.float16, ("sequential",))])
def test_low_precision_inputs_accumulate_in_float32(dtype, methods):
  rng = np.random.default_rng(11)
  x, dt, A, B, C, D, h0 = random_inputs(rng, L=64)
  lo = lambda v: jnp.asarray(v, dtype)
  up = lambda v: np.asarray(lo(v), np.float32)         # the values the kernel actually sees
  ref = scan(up(x), up(dt), A, up(B), up(C), D, method="sequential")
  for m in methods:
    y, h = scan(lo(x), lo(dt), A, lo(B), lo(C), D, method=m, return_state=True)
    assert y.dtype == dtype and h.dtype == jnp.float32
    # Only the final rounding to the low-precision dtype remains.
    eps = float(jnp.finfo(dtype).eps)
    assert np.all(np.abs(np.asarray(y, np.float32) - ref) <= eps * np.abs(ref) + 1e-3), m
    g = jax.jit(jax.grad(lambda x, dt: jnp.sum(selective_scan(x, dt, A, lo(B), lo(C), D, method=m)
                                               .astype(jnp.float32)), argnums=(0, 1)))(lo(x), lo(dt))
    assert g[0].dtype == dtype and all(np.all(np.isfinite(np.asarray(v, np.float32))) for v in g)


# -------------------------------------------------------------------- errors
@pytest.mark.parametrize("change, match", [
    (dict(dt=np.ones((2, 11, 4), np.float32)), "dt"),
    (dict(A=np.ones((4, 4), np.float32) * -1), "A must have shape"),
    (dict(A=np.ones((3, 4), np.float32)), "A must be real and non-positive"),
    (dict(B=np.ones((2, 10, 4), np.float32)), "B must have shape"),
    (dict(C=np.ones((2, 11, 5), np.float32)), "C must have shape"),
    (dict(D=np.ones((4,), np.float32)), "D must have shape"),
    (dict(initial_state=np.ones((2, 4, 3), np.float32)), "initial_state"),
    (dict(x=np.full((2, 11, 3), np.nan, np.float32)), "x holds NaN"),
    (dict(dt=-np.ones((2, 11, 3), np.float32)), "dt must be non-negative"),
    (dict(x=np.ones((2, 11, 3), np.int32)), "x must be a real floating"),
    (dict(method="fast"), "method"),
    (dict(chunk_size=0), "chunk_size"),
])
def test_bad_input_raises_value_error_naming_the_argument(change, match):
  x, dt, A, B, C, D, _ = random_inputs(np.random.default_rng(12))
  kw = dict(x=x, dt=dt, A=A, B=B, C=C, D=D)
  kw.update(change)
  with pytest.raises(ValueError, match=match):
    selective_scan(**kw)


def test_auto_rule():
  assert resolve_method("auto", backend="cpu") == "sequential"
  assert resolve_method("auto", backend="gpu") == "chunked"          # size unknown
  # Off the CPU by size (device.md, one H200): associative at the two benchmark shapes,
  # chunked at the paper model's temporal SSM (4e8 state elements).
  from nlosjax.ssm.scan import ASSOCIATIVE_MAX_SIZE
  assert resolve_method("auto", backend="gpu", size=64 * 512 * 32 * 16) == "associative"
  assert resolve_method("auto", backend="gpu", size=128 * 256 * 32 * 16) == "associative"
  assert resolve_method("auto", backend="gpu", size=3072 * 128 * 64 * 16) == "chunked"
  assert resolve_method("auto", backend="gpu", size=ASSOCIATIVE_MAX_SIZE) == "associative"
  assert resolve_method("auto", backend="gpu", size=ASSOCIATIVE_MAX_SIZE + 1) == "chunked"
  assert resolve_method("auto", backend="cpu", size=16) == "sequential"
  assert resolve_method("associative", backend="cpu") == "associative"
  with pytest.raises(ValueError, match="must be >= 0, got -1"):
    resolve_method("auto", backend="gpu", size=-1)
  with pytest.raises(ValueError, match="unknown scan method 'parallel'"):
    resolve_method("parallel", backend="cpu")


# ----------------------------------------------------------- bidirectional
def test_bidirectional_scan_combines_the_two_directions():
  rng = np.random.default_rng(13)
  x, dt, A, B, C, D, _ = random_inputs(rng)
  A_b = A * 2
  y_f = scan(x, dt, A, B, C, D)
  y_r = scan(x, dt, A_b, B, C, D, reverse=True)
  y = bidirectional_scan(x, dt, A, B, C, D, reverse_inputs={"A": A_b})
  np.testing.assert_allclose(y, (y_f + y_r) / 2, rtol=1e-6, atol=1e-6)
  s = bidirectional_scan(x, dt, A, B, C, D, reverse_inputs={"A": A_b}, combine="sum")
  np.testing.assert_allclose(s, y_f + y_r, rtol=1e-6, atol=1e-6)
  pair = bidirectional_scan(x, dt, A, B, C, D, combine="none")
  np.testing.assert_allclose(pair[1], scan(x, dt, A, B, C, D, reverse=True), rtol=1e-5, atol=1e-6)
  # Flip-equivariance with the two parameter sets swapped.
  flip = lambda v: v[:, ::-1]
  y2 = bidirectional_scan(flip(x), flip(dt), A_b, flip(B), flip(C), D, reverse_inputs={"A": A})
  np.testing.assert_allclose(flip(y2), y, rtol=1e-5, atol=1e-6)
  with pytest.raises(ValueError, match="reverse_inputs"):
    bidirectional_scan(x, dt, A, B, C, D, reverse_inputs={"E": A})
  with pytest.raises(ValueError, match="combine"):
    bidirectional_scan(x, dt, A, B, C, D, combine="max")


# -------------------------------------------------------------------- mixer
_MIXERS = {}


def _mixer(**cfg):
  """(module, params, input u [2, 12, d_model], jitted apply), built once per config."""
  key = tuple(sorted(cfg.items()))
  if key not in _MIXERS:
    m = MambaMixer(**cfg)
    u = jax.random.normal(jax.random.key(1), (2, 12, m.d_model))
    p = jax.jit(m.init)(jax.random.key(0), u)["params"]
    _MIXERS[key] = (m, flax.core.unfreeze(p), u, jax.jit(m.apply))
  return _MIXERS[key]


def test_mixer_initialisation_follows_mamba():
  _, p, _, _ = _mixer(d_model=64, d_state=16, n_residuals=4, param_dtype=jnp.bfloat16)
  d_inner, R, N = 128, 4, 16                               # dt_rank = ceil(64 / 16)
  shapes = jax.tree.map(np.shape, flax.core.unfreeze(p))
  assert shapes == {
      "in_proj": {"kernel": (64, 2 * d_inner)},
      "ssm": {"conv_kernel": (4, d_inner), "conv_bias": (d_inner,), "x_proj": {"kernel": (d_inner, R + 2 * N)},
              "dt_proj_kernel": (R, d_inner), "dt_proj_bias": (d_inner,), "A_log": (d_inner, N), "D": (d_inner,)},
      "out_proj": {"kernel": (d_inner, 64)}}
  p = {**p, **p["ssm"]}                                     # the SSM's names at the top, as below
  for name in ("A_log", "D", "dt_proj_bias"):
    assert p[name].dtype == jnp.float32, name          # fp32 whatever param_dtype is
  assert p["in_proj"]["kernel"].dtype == jnp.bfloat16
  a_log = np.log(np.arange(1, N + 1, dtype=np.float64)).astype(np.float32)    # S4D-real
  np.testing.assert_array_equal(p["A_log"], np.broadcast_to(a_log, (d_inner, N)))
  np.testing.assert_allclose(-np.exp(p["A_log"]), -np.broadcast_to(np.arange(1.0, N + 1), (d_inner, N)),
                             rtol=1e-6)
  np.testing.assert_array_equal(p["D"], np.ones(d_inner))
  dt = np.asarray(jax.nn.softplus(p["dt_proj_bias"]))
  assert dt.min() >= 1e-3 * (1 - 1e-5) and dt.max() <= 0.1 * (1 + 1e-5)
  assert dt.min() < 2e-3 and dt.max() > 0.05                # log-uniform over the whole range
  assert abs(np.median(np.log(dt)) - np.log(1e-2)) < 0.5    # geometric middle of [1e-3, 0.1]
  bounds = {("in_proj", "kernel"): 1 / math.sqrt(64), ("x_proj", "kernel"): 1 / math.sqrt(d_inner),
            ("dt_proj_kernel",): R ** -0.5, ("conv_kernel",): 0.5, ("conv_bias",): 0.5,
            ("out_proj", "kernel"): 1 / math.sqrt(d_inner) / math.sqrt(4)}
  for path, bound in bounds.items():
    v = p
    for k in path:
      v = v[k]
    v = np.abs(np.asarray(v, np.float32))
    # Uniform(+-bound): never beyond it (lecun_normal would be), and filling it.
    assert v.max() <= bound * 1.01 and v.max() > 0.9 * bound, (path, v.max(), bound)
  _, pc, _, _ = _mixer(d_model=16, d_state=4, dt_init="constant")
  np.testing.assert_allclose(pc["ssm"]["dt_proj_kernel"], 1.0)   # dt_rank 1 -> 1^-0.5


@pytest.mark.parametrize("direction", ["causal", "bidirectional"])
def test_mixer_matches_the_numpy_mamba_reference(direction):
  _, p, u, apply = _mixer(d_model=8, d_state=4, direction=direction)
  out = apply({"params": p}, u)
  ref = mixer_ref_np(p, u, d_state=4, bidirectional=direction == "bidirectional")
  assert out.shape == u.shape and out.dtype == jnp.float32
  assert rel_err(out, ref) < 1e-5


def test_causal_mixer_is_exactly_causal_and_bidirectional_is_not():
  t0 = 7
  for direction in ("causal", "bidirectional"):
    _, p, u, apply = _mixer(d_model=8, d_state=4, direction=direction)
    u2 = u.at[:, t0].add(1.0)
    y, y2 = np.asarray(apply({"params": p}, u)), np.asarray(apply({"params": p}, u2))
    changed = np.abs(y - y2).max(axis=(0, 2)) > 0                # per step
    assert np.all(changed[t0:]), direction
    if direction == "causal":
      assert np.array_equal(y[:, :t0], y2[:, :t0])               # bit-identical before t0
    else:
      assert np.all(changed[:t0])                                # sees the future


@pytest.mark.parametrize("conv", ["directional", "centered"])
def test_bidirectional_mixer_is_flip_equivariant_with_mirrored_params(conv):
  """mixer(flip(u); forward <-> reverse params swapped) == flip(mixer(u))."""
  # The shared centred conv mirrors onto itself with reversed taps when d_conv is odd.
  _, p, u, f = _mixer(d_model=8, d_state=4, d_conv=3 if conv == "centered" else 4,
                      direction="bidirectional", conv=conv)
  # Forward and reverse parameters swapped by hand (mirror_params, which the network's
  # rotation test uses, is checked against this below).
  mirrored = {**p, "ssm": dict(p["ssm"])}
  for k, v in p["ssm"].items():
    back = k.replace("dt_proj_", "dt_proj_b_") if k.startswith("dt_proj_") else k + "_b"
    if back in p["ssm"]:
      mirrored["ssm"][k], mirrored["ssm"][back] = p["ssm"][back], v
  if conv == "centered":
    mirrored["ssm"]["conv_kernel"] = p["ssm"]["conv_kernel"][::-1]
  from nlosjax.ssm.mamba import mirror_params
  by_function = mirror_params(p)
  if conv == "centered":
    by_function["ssm"]["conv_kernel"] = by_function["ssm"]["conv_kernel"][::-1]
  assert jax.tree.map(lambda a, b: bool(np.array_equal(a, b)), by_function, mirrored) == jax.tree.map(
      lambda a: True, mirrored)
  y, y_flip = f({"params": p}, u), f({"params": mirrored}, u[:, ::-1])
  assert rel_err(y_flip[:, ::-1], y) < 1e-5


def test_mixer_shared_params_bf16_and_gradients():
  _, ps, _, _ = _mixer(d_model=8, d_state=4, direction="bidirectional", share_params=True)
  assert not any(k.endswith("_b") or "_b_" in k for k in ps["ssm"])
  _, p, u, apply32 = _mixer(d_model=8, d_state=4)
  m = MambaMixer(d_model=8, d_state=4, dtype=jnp.bfloat16)
  loss = lambda p: jnp.sum(m.apply({"params": p}, u).astype(jnp.float32) ** 2)
  (l, g), y = jax.jit(lambda p: (jax.value_and_grad(loss)(p), m.apply({"params": p}, u)))(p)
  assert y.dtype == jnp.bfloat16 and np.all(np.isfinite(np.asarray(y, np.float32)))
  assert rel_err(np.asarray(y, np.float32), apply32({"params": p}, u)) < 0.05
  assert np.isfinite(l) and all(np.all(np.isfinite(np.asarray(v, np.float32)))
                                for v in jax.tree.leaves(g))
  with pytest.raises(ValueError, match="d_model"):
    m.apply({"params": p}, u[..., :4])
  with pytest.raises(ValueError, match="direction"):
    MambaMixer(d_model=8, direction="both").init(jax.random.key(0), u)
  with pytest.raises(ValueError, match="centered"):
    MambaMixer(d_model=8, conv="centered").init(jax.random.key(0), u)


def test_depthwise_conv_modes():
  rng = np.random.default_rng(14)
  x = rng.normal(size=(2, 9, 3)).astype(np.float32)
  k = rng.normal(size=(4, 3)).astype(np.float32)
  ref = np.swapaxes(_torch_causal_conv(np.swapaxes(x, 1, 2).astype(np.float64), k, None), 1, 2)
  np.testing.assert_allclose(depthwise_conv(x, k, mode="causal"), ref, rtol=1e-5, atol=1e-6)
  anti = depthwise_conv(x, k, mode="anticausal")
  np.testing.assert_allclose(anti, depthwise_conv(x[:, ::-1], k, mode="causal")[:, ::-1],
                             rtol=1e-6, atol=1e-6)
  with pytest.raises(ValueError, match="mode"):
    depthwise_conv(x, k, mode="same")
