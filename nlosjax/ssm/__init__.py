"""Selective state-space models (Mamba v1): scan kernels and a Flax mixer.

Public API::

    selective_scan       h_t = exp(dt_t A) h_{t-1} + dt_t B_t x_t,  y_t = <C_t, h_t> + D x_t
                         method: a name of METHODS (a kernel of nlosjax.ssm.scan, or "auto")
    bidirectional_scan   forward + reverse scans of one sequence, combined as Vision Mamba does
    resolve_method       the method "auto" picks for a shape and backend
    SelectiveSSM         Mamba's selective SSM (conv, projections of dt, B, C; scan), the one SSM
    MixerWidths          the widths every Mamba-style mixer shares (d_model, d_state, d_conv, expand, dt_rank)
    MambaMixer           Flax linen Mamba v1 mixer (projections and gate around a SelectiveSSM)
    mamba_dt_bias_init, s4d_real_a_log_init   Mamba's initialisers
"""

from nlosjax.ssm.mamba import MambaMixer, MixerWidths, SelectiveSSM, mamba_dt_bias_init, s4d_real_a_log_init
from nlosjax.ssm.scan import METHODS, bidirectional_scan, resolve_method, selective_scan

__all__ = [
    "selective_scan", "bidirectional_scan", "resolve_method", "METHODS", "MambaMixer", "MixerWidths", "SelectiveSSM",
    "mamba_dt_bias_init", "s4d_real_a_log_init",
]
