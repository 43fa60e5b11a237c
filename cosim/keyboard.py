"""Keyboard driving: arrow keys or WASD for throttle, brake and steering; R puts the car in
reverse and back in drive (the throttle then backs it up); M toggles manual and automatic
driving. One mapping, two front ends: PyBullet's 3D window (polled with
``getKeyboardEvents`` in the loop) and the Qt window (which feeds key presses to
:meth:`KeyboardControl.press` / :meth:`release`).

Keys are held, not tapped: throttle and brake ramp up while held and drop when released;
steering ramps towards full lock and recentres, as on a game pad.
"""
from __future__ import annotations

THROTTLE_KEYS = {"up", "w"}
BRAKE_KEYS = {"down", "s"}
LEFT_KEYS = {"left", "a"}
RIGHT_KEYS = {"right", "d"}
TOGGLE_KEYS = {"m"}
REVERSE_KEYS = {"r"}


class KeyboardControl:
    def __init__(self, ramp_per_s: float = 2.5, steer_per_s: float = 1.5):
        self.held: set = set()
        self.manual = False
        self.throttle = self.brake = self.steer = 0.0
        self.reverse = False          # the gear: reverse (R toggles it while driving by hand)
        self.ramp, self.steer_rate = ramp_per_s, steer_per_s

    def press(self, key: str) -> None:
        key = key.lower()
        if key in TOGGLE_KEYS:
            self.manual = not self.manual
            self.reverse = False
            return
        if key in REVERSE_KEYS:
            self.reverse = not self.reverse
            self.manual = True
            return
        self.held.add(key)
        if key in THROTTLE_KEYS | BRAKE_KEYS | LEFT_KEYS | RIGHT_KEYS:
            self.manual = True        # touching the controls takes over, as in a car

    def release(self, key: str) -> None:
        self.held.discard(key.lower())

    def update(self, dt: float) -> tuple[float, float, float] | None:
        """(throttle, brake, steer) for this step when driving by hand, else None."""
        if not self.manual:
            self.throttle = self.brake = self.steer = 0.0
            return None
        def ramp(v, on, rate):
            return min(1.0, v + rate * dt) if on else max(0.0, v - 2 * rate * dt)
        self.throttle = ramp(self.throttle, bool(self.held & THROTTLE_KEYS), self.ramp)
        self.brake = ramp(self.brake, bool(self.held & BRAKE_KEYS), self.ramp)
        want = (1.0 if self.held & LEFT_KEYS else 0.0) - (1.0 if self.held & RIGHT_KEYS else 0.0)
        step = self.steer_rate * dt
        self.steer += max(-step, min(step, want - self.steer))
        return self.throttle, self.brake, self.steer


def pybullet_keys(client: int, kb: KeyboardControl) -> None:
    """Feed PyBullet window key events (pressed / released) into `kb`."""
    import pybullet as pb

    names = {pb.B3G_UP_ARROW: "up", pb.B3G_DOWN_ARROW: "down", pb.B3G_LEFT_ARROW: "left",
             pb.B3G_RIGHT_ARROW: "right"}
    for code, state in pb.getKeyboardEvents(physicsClientId=client).items():
        name = names.get(code) or (chr(code) if 32 <= code < 127 else None)
        if name is None:
            continue
        if state & pb.KEY_WAS_TRIGGERED:
            kb.press(name)
        if state & pb.KEY_WAS_RELEASED:
            kb.release(name)
