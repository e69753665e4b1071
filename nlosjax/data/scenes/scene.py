"""A scene: its objects (:class:`SceneObject`), poses per frame (:class:`Scene`) and the draw (:func:`make_scene`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from nlosjax.data.scenes.motion import (
  Helix,
  Line,
  _axis_angle,
  _facing_rotation,
  _make_helix,
  _make_line,
  _random_rotation,
)
from nlosjax.data.scenes.params import GENERATOR_VERSION, PLANAR_KINDS, SceneParams
from nlosjax.data.scenes.shapes import _scale_shape, _scale_texture, _shape, _texture
from nlosjax.physics.setup import Setup


@dataclasses.dataclass(frozen=True, eq=False)
class SceneObject:
  """One rigid object.

  Attributes:
    kind: one of :data:`KINDS`.
    anchor: ``[3]`` world position (metres) of the local origin; for the
      dynamic object, its position at time 0 is ``Scene.helix`` at ``t = 0``.
    rotation: ``[3, 3]`` local-to-world rotation (columns: local axes in world).
    size: extent, metres.
    radius: bounding-sphere radius about the anchor, metres.
    shape: kind parameters: ``half_extents [3]`` (box, bar), ``radius``
      (sphere), ``major``/``minor`` (torus), ``polygons`` (tuple of ``[N, 2]``
      local outlines, even-odd rule; planar kinds), ``char`` (letter, digit).
    texture: ``{"name": ..., ...}`` (see :data:`TEXTURES`).
    dynamic: whether it follows the helix.
  """

  kind: str
  anchor: np.ndarray
  rotation: np.ndarray
  size: float
  radius: float
  shape: dict
  texture: dict
  dynamic: bool = False

  def describe(self) -> dict:
    """JSON-able summary (no outlines)."""
    shape = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.shape.items()
             if k != "polygons"}
    texture = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.texture.items()}
    return {"kind": self.kind, "dynamic": self.dynamic, "anchor": self.anchor.tolist(),
            "rotation": self.rotation.tolist(), "size": self.size, "radius": self.radius,
            "shape": shape, "texture": texture}




@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
  """Static objects plus one dynamic object on a path, over ``num_frames`` frames.

  Attributes:
    objects: the static objects, then the dynamic one (last).
    helix: the helix drawn for the dynamic object (its path unless ``line``).
    num_frames: ``F``.
    frame_rate: frames per second (frame ``f`` at ``t = f / frame_rate``).
    seed: the seed it was drawn from.
    line: the dynamic object's straight path, when its motion is ``"line"``.
    spin_axis, spin_speed: the dynamic object turns about ``spin_axis``
      ``[3]`` (unit, through its anchor) at ``spin_speed`` rad/s (0: it does not).
    deform_amplitude, deform_angle, deform_speed, deform_phase: the planar
      dynamic object's stretch ``exp(a sin(w t + phi))`` along the in-plane
      direction at ``deform_angle`` (radians from its local x axis), ``w``
      in rad/s; amplitude 0: rigid (:meth:`deformation`).
  """

  objects: tuple[SceneObject, ...]
  helix: Helix
  num_frames: int
  frame_rate: float
  seed: int
  line: Line | None = None
  spin_axis: np.ndarray | None = None
  spin_speed: float = 0.0
  deform_amplitude: float = 0.0
  deform_angle: float = 0.0
  deform_speed: float = 0.0
  deform_phase: float = 0.0

  @property
  def deforms(self) -> bool:
    """Whether the dynamic object changes shape over the sequence (non-rigid motion)."""
    return self.deform_amplitude > 0.0

  @property
  def motion(self) -> str:
    """``"line"`` or ``"helix"``."""
    return "helix" if self.line is None else "line"

  @property
  def path(self) -> Helix | Line:
    """The dynamic object's path."""
    return self.helix if self.line is None else self.line

  @property
  def dynamic_index(self) -> int:
    """Index of the dynamic object in :attr:`objects`."""
    return next(i for i, o in enumerate(self.objects) if o.dynamic)

  @property
  def times(self) -> np.ndarray:
    """``[F]`` float64 frame times, seconds."""
    return np.arange(self.num_frames) / self.frame_rate

  @property
  def trajectory(self) -> np.ndarray:
    """``[F, 3]`` float64 anchor position of the dynamic object per frame, metres."""
    return self.path.positions(self.times)

  def anchor(self, index: int, frame: int) -> np.ndarray:
    """``[3]`` world position of object ``index`` at ``frame``."""
    obj = self.objects[index]
    if obj.dynamic:
      return self.path.positions([frame / self.frame_rate])[0]
    return obj.anchor

  def rotation(self, index: int, frame: int) -> np.ndarray:
    """``[3, 3]`` local-to-world rotation of object ``index`` at ``frame``."""
    obj = self.objects[index]
    if not obj.dynamic or self.spin_speed == 0.0:
      return obj.rotation
    return _axis_angle(self.spin_axis, self.spin_speed * frame / self.frame_rate) @ obj.rotation

  def deformation(self, index: int, frame: int) -> np.ndarray:
    """``[2, 2]`` in-plane map of object ``index`` at ``frame`` (local x, y; identity if rigid).

    ``M = R(angle) diag(e^s, e^-s) R(angle)^T`` with ``s = a sin(w t + phi)``:
    symmetric, determinant 1 (areas kept), singular values ``e^|s| <= e^a``.
    """
    obj = self.objects[index]
    if not obj.dynamic or not self.deforms:
      return np.eye(2)
    stretch = self.deform_amplitude * math.sin(self.deform_speed * frame / self.frame_rate
                                               + self.deform_phase)
    c, s = math.cos(self.deform_angle), math.sin(self.deform_angle)
    rot = np.array([[c, -s], [s, c]])
    return rot @ np.diag([math.exp(stretch), math.exp(-stretch)]) @ rot.T

  def posed(self, index: int, frame: int) -> SceneObject:
    """Object ``index`` at its anchor, rotation and (planar, non-rigid) deformation of ``frame``.

    A deformed object's ``shape`` gains ``"warp"``: the ``[2, 2]``
    :meth:`deformation` that maps its reference outline (``polygons``) and
    texture coordinates to the frame's.
    """
    obj = self.objects[index]
    if not obj.dynamic:
      return obj
    posed = dataclasses.replace(obj, anchor=self.anchor(index, frame),
                                rotation=self.rotation(index, frame))
    if self.deforms:
      posed = dataclasses.replace(posed, shape={**obj.shape, "warp": self.deformation(index, frame)})
    return posed

  def describe(self) -> dict:
    """JSON-able summary of the scene (objects, path, frames)."""
    d = {"generator_version": GENERATOR_VERSION, "seed": self.seed,
         "num_frames": self.num_frames, "frame_rate": self.frame_rate,
         "helix": self.helix.describe(), "objects": [o.describe() for o in self.objects]}
    if self.line is not None:
      d["line"] = self.line.describe()
    if self.spin_speed:
      d["spin"] = {"axis": self.spin_axis.tolist(), "speed": self.spin_speed}
    if self.deforms:
      d["deform"] = {"amplitude": self.deform_amplitude, "angle": self.deform_angle,
                     "speed": self.deform_speed, "phase": self.deform_phase}
    return d




def _make_object(rng, params: SceneParams, kinds, dynamic: bool) -> SceneObject:
  kind = str(rng.choice(list(kinds)))
  size = float(rng.uniform(*params.size_range))
  shape, radius = _shape(rng, kind, size, params.glyph_weights)
  cap = 0.49 * (params.depth_range[1] - params.depth_range[0])
  if radius > cap:  # the bounding sphere must fit the depth range
    shape, size, radius = _scale_shape(shape, cap / radius), size * cap / radius, cap
  if kind in PLANAR_KINDS:
    rotation = _facing_rotation(rng, params.max_tilt)
  else:
    rotation = _random_rotation(rng)
  texture = _texture(rng, size, force=kind == "plate", probability=params.texture_probability,
                     albedo_range=params.albedo_range)
  return SceneObject(kind=kind, anchor=np.zeros(3), rotation=rotation, size=size, radius=radius,
                     shape=shape, texture=texture, dynamic=dynamic)




def make_scene(seed: int, params: SceneParams | Mapping | None = None, num_frames: int = 32,
               setup: Setup | None = None) -> Scene:
  """Draw a dynamic scene.

  Args:
    seed: integer seed (``numpy.random.default_rng(seed)`` draws everything).
    params: :class:`SceneParams` or a dict of its fields (default: defaults).
    num_frames: ``F >= 1`` frames, at ``params.frame_rate``.
    setup: optional capture to check the scene box against (depth and wall).
  Returns:
    a :class:`Scene` with ``U{num_static}`` static objects and one dynamic object.
  Raises:
    ValueError: for a bad argument, or scene bounds that do not fit ``setup``.
  """
  if params is None:
    params = SceneParams()
  elif isinstance(params, Mapping):
    params = SceneParams.from_dict(params)
  elif not isinstance(params, SceneParams):
    raise ValueError(f"params must be a SceneParams or dict, got {type(params).__name__}")
  if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or num_frames < 1:
    raise ValueError(f"num_frames must be an integer >= 1, got {num_frames!r}")
  if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
    raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
  if setup is not None:
    params.check_setup(setup)
  rng = np.random.default_rng(int(seed))
  duration = (num_frames - 1) / params.frame_rate

  dyn = _make_object(rng, params, params.dynamic_kinds, dynamic=True)
  # Non-rigid stretch, from a stream of its own; its bounding sphere grows by the largest stretch.
  deform = {}
  if params.deform[1] > 0 and dyn.kind in PLANAR_KINDS:
    deform_rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(5,)))
    deform = {"deform_amplitude": float(deform_rng.uniform(*params.deform)),
              "deform_angle": float(deform_rng.uniform(0, math.pi)),
              "deform_speed": float(deform_rng.uniform(*params.helix_speed)),
              "deform_phase": float(deform_rng.uniform(0, 2 * math.pi))}
    grown = dyn.radius * math.exp(deform["deform_amplitude"])
    cap = 0.49 * (params.depth_range[1] - params.depth_range[0])
    if grown > cap:   # as _make_object: the (stretched) bounding sphere must fit the depth range
      k = cap / grown
      dyn = dataclasses.replace(dyn, shape=_scale_shape(dyn.shape, k), size=dyn.size * k,
                                radius=dyn.radius * k, texture=_scale_texture(dyn.texture, k))
    dyn = dataclasses.replace(dyn, radius=dyn.radius * math.exp(deform["deform_amplitude"]))
  helix = _make_helix(rng, params, dyn.radius, duration)
  # Motion and spin come from a stream of their own: the default scenes stay as they were.
  motion_rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(4,)))
  motion = str(motion_rng.choice(list(params.motions))) if len(params.motions) > 1 else params.motions[0]
  line = _make_line(motion_rng, params, dyn.radius, duration) if motion == "line" else None
  spin_axis, spin_speed = None, 0.0
  if params.spin_speed[1] > 0:
    spin_axis = motion_rng.normal(size=3)
    spin_axis /= np.linalg.norm(spin_axis)
    spin_speed = float(motion_rng.uniform(*params.spin_speed)) * float(motion_rng.choice([-1.0, 1.0]))
  moving = line if line is not None else helix
  path = moving.positions(np.linspace(0.0, duration, 256) if duration > 0 else np.zeros(1))
  dyn = dataclasses.replace(dyn, anchor=moving.positions([0.0])[0])

  statics = []
  n_static = int(rng.integers(params.num_static[0], params.num_static[1] + 1))
  L = params.lateral_extent
  for _ in range(n_static):
    obj = _make_object(rng, params, params.kinds, dynamic=False)
    z_lo, z_hi = params.depth_range[0] + obj.radius, params.depth_range[1] - obj.radius
    anchor = None
    for _ in range(100):  # rejection sampling of a non-overlapping place
      anchor = np.array([rng.uniform(-L, L), rng.uniform(-L, L), rng.uniform(z_lo, z_hi)])
      ok = np.min(np.linalg.norm(path - anchor, axis=1)) > obj.radius + dyn.radius + params.min_gap
      ok = ok and all(np.linalg.norm(o.anchor - anchor) > obj.radius + o.radius + params.min_gap
                      for o in statics)
      if ok:
        break
    statics.append(dataclasses.replace(obj, anchor=anchor))
  return Scene(objects=tuple(statics) + (dyn,), helix=helix, num_frames=int(num_frames),
               frame_rate=params.frame_rate, seed=int(seed), line=line, spin_axis=spin_axis,
               spin_speed=spin_speed, **deform)
