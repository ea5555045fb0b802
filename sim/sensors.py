"""Sensor models of the simulated robot: wheel odometry, magnetic compass, sonar ring."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.geometry import ray_cast, wrap_angle
from sim.robot import Motion, Pose
from sim.world import World

_DEG = math.pi / 180.0


# -- odometry ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class OdometryParams:
    distance_scale_error: float = 0.015  # systematic: the wheels report (1 + this) x the distance
    distance_noise_m_per_sqrt_m: float = 0.01  # white distance noise, std per sqrt(metre) travelled
    rotation_scale_error: float = 0.03  # systematic: the wheels report (1 + this) x every turn
    rotation_drift_rad_per_m: float = 1.0 * _DEG  # systematic heading drift per metre travelled (curving)
    rotation_noise_rad_per_sqrt_m: float = 0.5 * _DEG  # white heading noise, std per sqrt(metre) travelled
    rotation_noise_rad_per_sqrt_rad: float = 0.02  # white heading noise, std per sqrt(radian) turned
    slip_probability: float = 0.005  # chance per moving step of a wheel slip
    slip_distance_fraction: float = 0.3  # std of a slip's distance error, as a fraction of the step
    slip_rotation_rad: float = 2.0 * _DEG  # std of a slip's heading error


class OdometryModel:
    """Wheel odometry: what the encoders report for one step of true motion.

    Raw odometry curves (the paper's Figure 6, left): a constant drift per metre plus a scale error
    on every turn, on top of white noise and occasional slips.
    """

    def __init__(self, params: OdometryParams = OdometryParams()) -> None:
        self.params = params

    def measure(self, motion: Motion, rng: np.random.Generator) -> tuple[float, float]:
        """``(distance_m, rotation_rad)`` reported for ``motion``; draws 4 normals and 1 uniform."""
        p = self.params
        z = rng.standard_normal(4)
        u = rng.random()
        ds, dth = motion.distance_m, motion.rotation_rad
        dist = abs(ds)
        if dist == 0.0 and dth == 0.0:
            return 0.0, 0.0
        meas_d = ds * (1.0 + p.distance_scale_error) + p.distance_noise_m_per_sqrt_m * math.sqrt(dist) * z[0]
        meas_r = (dth * (1.0 + p.rotation_scale_error) + p.rotation_drift_rad_per_m * dist
                  + p.rotation_noise_rad_per_sqrt_m * math.sqrt(dist) * z[1]
                  + p.rotation_noise_rad_per_sqrt_rad * math.sqrt(abs(dth)) * z[2])
        if dist > 0.0 and u < p.slip_probability:
            meas_d += p.slip_distance_fraction * ds * z[3]
            meas_r += p.slip_rotation_rad * z[3]
        return float(meas_d), float(meas_r)


# -- compass -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CompassParams:
    noise_rad: float = 2.0 * _DEG  # std of the white noise on every reading
    disturbance_scale: float = 1.0  # multiplies every magnetic disturbance of the world (0: none)


class CompassModel:
    """Absolute heading plus white noise plus the world's smooth magnetic disturbances.

    A disturbance deflects the reading by ``deviation_deg * (1 - (d / radius)^2)^2`` at distance
    ``d < radius`` from its centre: largest at the centre, fading smoothly to zero at the radius.
    """

    def __init__(self, world: World, params: CompassParams = CompassParams()) -> None:
        self.params = params
        self._dist = tuple((m.x_m, m.y_m, m.radius_m * m.radius_m, m.deviation_deg * _DEG * params.disturbance_scale)
                           for m in world.magnetic_disturbances)

    def deviation_rad(self, x: float, y: float) -> float:
        """Deflection of the compass at ``(x, y)`` (no noise)."""
        total = 0.0
        for cx, cy, r2, dev in self._dist:
            d2 = (x - cx) ** 2 + (y - cy) ** 2
            if d2 < r2:
                f = 1.0 - d2 / r2
                total += dev * f * f
        return total

    def measure(self, pose: Pose, rng: np.random.Generator) -> float:
        """Heading reported at ``pose``, in (-pi, pi]; draws 1 normal."""
        z = rng.standard_normal()
        return wrap_angle(float(pose[2] + self.deviation_rad(pose[0], pose[1]) + self.params.noise_rad * z))


# -- sonar -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SonarParams:
    transducers: int = 16  # number of transducers in the ring
    spacing_rad: float = 22.5 * _DEG  # bearing between neighbouring transducers
    beam_width_rad: float = 25.0 * _DEG  # full opening angle of each beam cone
    rays_per_beam: int = 5  # rays cast across each cone; the nearest hit is the echo
    min_range_m: float = 0.15  # echoes nearer than this read as this
    max_range_m: float = 6.5  # no echo reads as this
    range_noise_m: float = 0.02  # std of the range noise at zero range
    range_noise_fraction: float = 0.01  # the std grows by this fraction of the range
    miss_probability: float = 0.02  # chance a beam loses its echo whatever the geometry
    specular_start_rad: float = 40.0 * _DEG  # incidence beyond which the echo may be reflected away
    specular_max_probability: float = 0.8  # chance the echo is reflected away at grazing incidence


class SonarModel:
    """A ring of sonar transducers; ranges are measured from the robot's centre.

    Each beam cone is sampled by ``rays_per_beam`` rays and the nearest hit is the beam's echo. It
    is lost (specular reflection: the reading is ``max_range_m``) with a probability rising
    linearly from 0 at ``specular_start_rad`` incidence to ``specular_max_probability`` at grazing
    incidence, and with ``miss_probability`` whatever the geometry; otherwise range noise is added.
    """

    def __init__(self, params: SonarParams = SonarParams()) -> None:
        if params.transducers < 1 or params.rays_per_beam < 1:
            raise ValueError("SonarParams: transducers and rays_per_beam must be at least 1")
        self.params = params
        self.bearings = wrap_angle(np.arange(params.transducers) * params.spacing_rad)
        if params.rays_per_beam == 1:
            spread = np.zeros(1)
        else:
            spread = np.linspace(-0.5 * params.beam_width_rad, 0.5 * params.beam_width_rad, params.rays_per_beam)
        self._ray_offsets = (self.bearings[:, None] + spread[None, :]).ravel()

    @property
    def rays(self) -> int:
        """Rays cast per scan."""
        return self._ray_offsets.shape[0]

    def measure(self, pose: Pose, world: World, rng: np.random.Generator) -> np.ndarray:
        """Ranges of every transducer at ``pose``; draws 2 uniforms and 1 normal per transducer."""
        p = self.params
        n, k = p.transducers, p.rays_per_beam
        u_spec = rng.random(n)
        u_miss = rng.random(n)
        z = rng.standard_normal(n)
        walls = world.walls_near(pose[0], pose[1], p.max_range_m)
        ranges, _, cos_inc = ray_cast(np.array(pose[:2]), pose[2] + self._ray_offsets, walls, p.max_range_m)
        ranges = ranges.reshape(n, k)
        best = np.argmin(ranges, axis=1)
        rows = np.arange(n)
        echo = ranges[rows, best]
        inc = np.arccos(np.clip(cos_inc.reshape(n, k)[rows, best], 0.0, 1.0))
        frac = np.clip((inc - p.specular_start_rad) / (0.5 * math.pi - p.specular_start_rad), 0.0, 1.0)
        hit = (echo < p.max_range_m) & (u_spec >= p.specular_max_probability * frac) & (u_miss >= p.miss_probability)
        noisy = echo + (p.range_noise_m + p.range_noise_fraction * echo) * z
        noisy = np.clip(noisy, p.min_range_m, np.nextafter(p.max_range_m, 0.0))
        return np.where(hit, noisy, p.max_range_m)
