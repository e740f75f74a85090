"""Machine facts recorded with every benchmark."""

from __future__ import annotations

import platform
import subprocess


def cpu_name() -> str:
    """The CPU model from lscpu (or what the platform module knows)."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        for line in out.splitlines():
            if line.startswith("Model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
