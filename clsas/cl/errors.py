"""The device layer's two errors: no OpenCL device, and a kernel that will not build."""

from __future__ import annotations

__all__ = ["BuildError", "OpenCLUnavailable"]


class OpenCLUnavailable(RuntimeError):
    """No usable OpenCL platform or device."""


class BuildError(RuntimeError):
    """An OpenCL program or kernel variant could not be built; ``.log`` holds the build log."""

    def __init__(self, files: tuple[str, ...], device: str, reason: str, build_log: str = ""):
        self.files = tuple(files)
        self.device = device
        self.reason = reason
        self.log = build_log
        text = f"building {', '.join(files)} for {device}: {reason}"
        if build_log.strip():
            text += f"\n--- build log ---\n{build_log.strip()[-6000:]}"
        super().__init__(text)
