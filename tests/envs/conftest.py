"""MuJoCo renders offscreen through EGL on CPU-only machines; it must be chosen before import."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
