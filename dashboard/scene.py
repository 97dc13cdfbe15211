"""The 3D view: the vehicle framed and followed, its trail and the reference path always visible.

- the vehicle (body, rotors, its frame), a drop line to the floor and a shadow disc under it, so
  its height reads at a glance;
- the trail (where it flew, last ``TRAIL_S``) and the reference path (what it was asked to fly,
  same span) as lines a few pixels wide — visible whatever the zoom, also while it hovers on a
  point (where the old dots hid under the body) — and a sphere at the current reference;
- every browser's camera follows the vehicle: it is moved by the vehicle's (smoothed) motion, so
  an operator's own orbit and zoom are kept; a page opens ``VIEW_DISTANCE_M`` from the vehicle;
- the simulator's ramp when the scenario is ``ood_slope``.
"""
from __future__ import annotations

import math

import numpy as np

from neso.rotations import world_from_body_zyx

VIEW_OFFSET_M = np.array([0.9, -1.2, 0.55])  # a page opens here relative to the vehicle (1.6 m away)
FOLLOW_SMOOTHING = 0.35  # low-pass of the followed point per update (mocap noise would shake the view)
FOLLOW_MIN_STEP_M = 0.003  # smaller moves of the followed point are not sent
TRAIL_POINTS = 1500  # 30 s at 50 Hz (the model keeps as many)
TRAIL_RGB = (30, 110, 220)
REFERENCE_RGB = (240, 140, 20)


def quat_wxyz(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    r = world_from_body_zyx(roll, pitch, yaw)
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2.0
    if w < 1e-6:
        return (0.0, 1.0, 0.0, 0.0)
    return (w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w))


def polyline_segments(points: np.ndarray) -> np.ndarray:
    """(N, 3) points → (N−1, 2, 3) segments joining them (a single degenerate one for N < 2)."""
    p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    if len(p) < 2:
        p = np.zeros((2, 3), np.float32) if len(p) == 0 else np.repeat(p, 2, axis=0)
    return np.stack([p[:-1], p[1:]], axis=1)


class Scene:
    """Builds the 3D scene once; :meth:`update` moves it to a vehicle's newest state."""

    def __init__(self, server) -> None:
        self.server = server
        s = server.scene
        s.set_up_direction("+z")
        # shadows and the image-based environment light cost most of a software-rendered frame
        # (Chromium without a GPU: 4 fps with them, see dashboard/README.md); plain lights instead
        s.configure_default_lights(cast_shadow=False)
        s.configure_environment_map(hdri=None)
        server.initial_camera.position = tuple(np.array([0.0, 0.0, 1.0]) + VIEW_OFFSET_M)
        server.initial_camera.look_at = (0.0, 0.0, 1.0)
        s.add_grid("/ground", width=6.0, height=6.0, cell_size=0.25, section_size=1.0, plane_color=(236, 240, 236),
                   plane_opacity=0.6)
        s.add_frame("/world", axes_length=0.3, axes_radius=0.006)
        self.vehicle = s.add_frame("/vehicle", axes_length=0.2, axes_radius=0.008)
        s.add_box("/vehicle/body", dimensions=(0.16, 0.16, 0.05), color=(40, 60, 90))
        for i, angle in enumerate((math.pi / 4, -math.pi / 4)):  # the two arms, corner to corner
            s.add_box(f"/vehicle/arm{i}", dimensions=(0.37, 0.018, 0.012), color=(40, 60, 90),
                      wxyz=(math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)))
        for i, (x, y) in enumerate(((0.13, 0.13), (-0.13, 0.13), (-0.13, -0.13), (0.13, -0.13))):
            s.add_cylinder(f"/vehicle/rotor{i}", radius=0.065, height=0.012,
                           color=(210, 70, 50) if x > 0 else (80, 80, 80), position=(x, y, 0.02))
        self.drop = s.add_line_segments("/vehicle_drop", polyline_segments(np.zeros((2, 3))), (120, 120, 120),
                                        thickness=1.5, thickness_units="screen")
        self.shadow = s.add_cylinder("/vehicle_shadow", radius=0.12, height=0.002, color=(90, 90, 90), opacity=0.35)
        self.trail = s.add_line_segments("/trail", polyline_segments(np.zeros((2, 3))), TRAIL_RGB, thickness=3.0,
                                         thickness_units="screen")
        self.ref_path = s.add_line_segments("/reference_path", polyline_segments(np.zeros((2, 3))), REFERENCE_RGB,
                                            thickness=2.0, thickness_units="screen")
        self.ref_point = s.add_icosphere("/reference", radius=0.025, color=REFERENCE_RGB, cast_shadow=False)
        self.slope = None
        self._scenario_drawn = ""
        self._followed: np.ndarray | None = None  # the smoothed vehicle position the cameras follow
        self._framed_clients: set[int] = set()
        server.on_client_disconnect(lambda client: self._framed_clients.discard(client.client_id))

    # -- camera ------------------------------------------------------------------------------
    def frame(self, client) -> None:
        """Point a page's camera at the vehicle from ``VIEW_OFFSET_M`` (once, at its first camera
        report: a pose sent before the page set its camera up would be overwritten)."""
        if client.client_id in self._framed_clients:
            return
        self._framed_clients.add(client.client_id)
        target = self._followed if self._followed is not None else np.array([0.0, 0.0, 1.0])
        client.camera.position = tuple(target + VIEW_OFFSET_M)  # moves its look-at along ...
        client.camera.look_at = tuple(target)  # ... then onto the vehicle

    def _follow(self, pos: np.ndarray) -> None:
        """Every page's camera looks at the vehicle's (smoothed) position from where its operator
        put it: the offset camera − look-at of its last report (orbit and zoom) is kept. Absolute,
        not step by step: a camera report older than a move would otherwise undo that move."""
        if self._followed is None:
            self._followed = pos.copy()
            return
        target = self._followed + FOLLOW_SMOOTHING * (pos - self._followed)
        if np.linalg.norm(target - self._followed) < FOLLOW_MIN_STEP_M:
            return
        self._followed = target
        for client in self.server.get_clients().values():
            if client.client_id not in self._framed_clients:
                continue  # not framed yet: its camera state is not known
            try:
                cam = client.camera
                cam.position = target + (cam.position - cam.look_at)  # translates its look-at onto the target
            except RuntimeError as exc:  # seen once: viser's per-client state changing under a (dis)connect
                print(f"[dashboard] camera of client {client.client_id} not moved: {exc}", flush=True)

    # -- frames ------------------------------------------------------------------------------
    def update(self, state, trail, ref_trail, reference) -> None:
        """The vehicle at ``state`` (a StateMsg), its trail and reference path (sequences of
        positions, oldest first), the current reference (a ReferenceMsg or None)."""
        pos = np.array(state.pos_enu_m, dtype=float)
        self.vehicle.position = pos
        self.vehicle.wxyz = np.array(quat_wxyz(state.roll_rad, state.pitch_rad, state.yaw_rad))
        floor = np.array([pos[0], pos[1], 0.0])
        self.drop.points = polyline_segments(np.array([pos, floor]))
        self.shadow.position = floor + np.array([0.0, 0.0, 0.001])
        if len(trail) > 1:
            self.trail.points = polyline_segments(np.array(trail, dtype=np.float32)[-TRAIL_POINTS:])
        if len(ref_trail) > 1:
            self.ref_path.points = polyline_segments(np.array(ref_trail, dtype=np.float32)[-TRAIL_POINTS:])
        if reference is not None:
            self.ref_point.position = np.array(reference.pos_enu_m)
        self.ref_point.visible = reference is not None
        self._follow(pos)

    def show_scenario(self, scenario: str) -> None:
        """The simulated ramp under ``ood_slope`` (drawn as the simulator simulates it)."""
        if scenario == self._scenario_drawn:
            return
        self._scenario_drawn = scenario
        if self.slope is not None:
            self.slope.remove()
            self.slope = None
        if scenario == "ood_slope":
            from sim.terrain import SlopeTerrain

            t = SlopeTerrain()
            x0, x1, tan_s = t.landing_x_m + t.edge_offset_m, 2.5, math.tan(math.radians(t.slope_deg))
            verts = np.array([[x0, -2.5, 0.0], [x1, -2.5, (x1 - x0) * tan_s], [x1, 2.5, (x1 - x0) * tan_s],
                              [x0, 2.5, 0.0]], dtype=np.float32)
            self.slope = self.server.scene.add_mesh_simple("/slope", verts, np.array([[0, 1, 2], [0, 2, 3]]),
                                                           color=(160, 130, 90), opacity=0.7, side="double")
