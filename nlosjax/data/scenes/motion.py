"""Paths and orientations: the dynamic object's :class:`Helix` or :class:`Line`, random rotations."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from nlosjax.data.scenes.params import SceneParams


@dataclasses.dataclass(frozen=True)
class Helix:
  """A helical path ``p(t) = center + r (cos th u + sin th v) + pitch * (th - phase) / (2 pi) * axis``.

  with ``th = phase + angular_speed * t`` (``t`` seconds) and ``v = axis x u``.

  Attributes:
    center: ``[3]`` a point on the helix axis, metres.
    axis: ``[3]`` unit axis direction.
    ref: ``[3]`` unit vector orthogonal to ``axis`` (``th = 0`` direction).
    radius: metres.
    pitch: axial advance per turn (signed), metres.
    phase: ``th`` at ``t = 0``, radians.
    angular_speed: radians per second (signed).
  """

  center: np.ndarray
  axis: np.ndarray
  ref: np.ndarray
  radius: float
  pitch: float
  phase: float
  angular_speed: float

  def positions(self, times) -> np.ndarray:
    """``[N, 3]`` float64 positions (metres) at ``times`` ``[N]`` (seconds)."""
    t = np.asarray(times, np.float64).reshape(-1)
    swept = self.angular_speed * t
    th = self.phase + swept
    v = np.cross(self.axis, self.ref)
    return (self.center[None] + self.radius * (np.cos(th)[:, None] * self.ref[None]
                                               + np.sin(th)[:, None] * v[None])
            + (self.pitch * swept / (2 * math.pi))[:, None] * self.axis[None])

  def describe(self) -> dict:
    return {"center": self.center.tolist(), "axis": self.axis.tolist(), "ref": self.ref.tolist(),
            "radius": self.radius, "pitch": self.pitch, "phase": self.phase,
            "angular_speed": self.angular_speed}


@dataclasses.dataclass(frozen=True)
class Line:
  """A straight path at constant velocity: ``p(t) = start + (end - start) t / duration``.

  Attributes:
    start, end: ``[3]`` positions at ``t = 0`` and ``t = duration``, metres.
    duration: seconds (0 for a one-frame scene: the path is ``start``).
  """

  start: np.ndarray
  end: np.ndarray
  duration: float

  def positions(self, times) -> np.ndarray:
    """``[N, 3]`` float64 positions (metres) at ``times`` ``[N]`` (seconds)."""
    t = np.asarray(times, np.float64).reshape(-1)
    u = t / self.duration if self.duration > 0 else np.zeros_like(t)
    return self.start[None] + u[:, None] * (self.end - self.start)[None]

  def describe(self) -> dict:
    return {"start": self.start.tolist(), "end": self.end.tolist(), "duration": self.duration}




def _random_rotation(rng) -> np.ndarray:
  """Uniform random rotation matrix (from a unit quaternion)."""
  q = rng.normal(size=4)
  w, x, y, z = q / np.linalg.norm(q)
  return np.array([
      [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
  ])


def _axis_angle(axis, angle) -> np.ndarray:
  axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
  k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
  return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def _facing_rotation(rng, max_tilt) -> np.ndarray:
  """In-plane spin, then a tilt of the normal (local z) by at most ``max_tilt`` from world z."""
  spin = _axis_angle([0, 0, 1], rng.uniform(-math.pi / 6, math.pi / 6))
  phi = rng.uniform(0, 2 * math.pi)
  tilt = _axis_angle([math.cos(phi), math.sin(phi), 0.0], rng.uniform(0, max_tilt))
  return tilt @ spin




def _orthonormal(axis) -> np.ndarray:
  """A unit vector orthogonal to ``axis``."""
  e = np.eye(3)[int(np.argmin(np.abs(axis)))]
  u = np.cross(axis, e)
  return u / np.linalg.norm(u)


def _make_helix(rng, params: SceneParams, obj_radius: float, duration: float) -> Helix:
  """A random helix whose path (over ``duration`` s) keeps the object inside the scene box."""
  axis = rng.normal(size=3)
  axis /= np.linalg.norm(axis)
  ref = _orthonormal(axis)
  radius = float(rng.uniform(*params.helix_radius))
  pitch = float(rng.uniform(*params.helix_pitch)) * float(rng.choice([-1.0, 1.0]))
  phase = float(rng.uniform(0, 2 * math.pi))
  speed = float(rng.uniform(*params.helix_speed)) * float(rng.choice([-1.0, 1.0]))
  L = params.lateral_extent
  z_lo, z_hi = params.depth_range[0] + obj_radius, params.depth_range[1] - obj_radius
  box_lo, box_hi = np.array([-L, -L, z_lo]), np.array([L, L, z_hi])
  times = np.linspace(0.0, duration, 256) if duration > 0 else np.zeros(1)
  # Shrink radius and pitch until the path fits the box; then place its centre uniformly.
  for _ in range(60):
    path = Helix(np.zeros(3), axis, ref, radius, pitch, phase, speed).positions(times)
    lo, hi = path.min(0), path.max(0)
    slack = (box_hi - box_lo) - (hi - lo)
    if np.all(slack >= 0):
      break
    radius *= 0.8
    pitch *= 0.8
  else:
    raise ValueError("cannot fit the helix into the scene box; widen depth_range or lateral_extent")
  center = rng.uniform(box_lo - lo, np.maximum(box_hi - hi, box_lo - lo))
  return Helix(center, axis, ref, radius, pitch, phase, speed)


def _make_line(rng, params: SceneParams, obj_radius: float, duration: float) -> Line:
  """A straight path between two uniform points of the scene box (the object stays inside)."""
  L = params.lateral_extent
  lo = np.array([-L, -L, params.depth_range[0] + obj_radius])
  hi = np.array([L, L, params.depth_range[1] - obj_radius])
  return Line(rng.uniform(lo, hi), rng.uniform(lo, hi), float(duration))
