"""The spatial-temporal Mamba network for dynamic confocal NLOS (paper Sec. 4) in Flax linen.

Public API::

    ModelConfig            frozen hyper-parameters + the Setup (presets: .cpu(), .paper(), .from_setup())
    STMambaNet             [B, F, T, h, w] counts -> {transient, volume, intensity, depth, scale}
    model_summary          parameter count and FLOPs per frame, without allocating
    underscan              [..., T, H, W] -> the [..., T, h, w] scan points the model reads
    STMambaBlock           temporal (causal) + spatial (bidirectional) SSM block
    CrossSTMambaBlock      reference / neighbour branches under a shared gate
    SelectiveSSM           the SSM of a Mamba mixer (no projections, no gate)
    InterleavedExtraction, TransientSpreading, VolumeReconstruction, FeatureTransform,
    ResBlock3D, InterlacedResBlock, soft_projection     the other blocks
"""

from nlosjax.models.blocks import (
                                   InterlacedResBlock,
                                   InterleavedExtraction,
                                   ResBlock3D,
                                   TransientSpreading,
                                   VolumeReconstruction,
)
from nlosjax.models.network import (
                                   ModelConfig,
                                   STMambaNet,
                                   count_params,
                                   format_summary,
                                   input_scale,
                                   model_summary,
                                   underscan,
)
from nlosjax.models.physics_layer import FeatureTransform, coarsen_setup, physics_window, soft_projection
from nlosjax.models.stmamba import BLOCK_MIXERS, CrossSTMambaBlock, SelectiveSSM, STMambaBlock, mirror_spatial_params

__all__ = [
    "ModelConfig", "STMambaNet", "model_summary", "format_summary", "count_params", "underscan",
    "input_scale", "STMambaBlock", "CrossSTMambaBlock", "SelectiveSSM", "BLOCK_MIXERS",
    "mirror_spatial_params", "InterleavedExtraction", "TransientSpreading",
    "VolumeReconstruction", "FeatureTransform", "ResBlock3D", "InterlacedResBlock",
    "soft_projection", "coarsen_setup", "physics_window",
]
