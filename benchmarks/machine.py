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


def release_compiled() -> None:
    """Drop every compiled executable of this process (``jax.clear_caches``). A script that
    runs many scenes one after another compiles new segments for each (capacities differ
    from run to run), and every executable keeps memory mappings of its machine code: past
    the kernel's limit of 65,530 per process (vm.max_map_count) the next compilation fails
    ("LLVM compilation error: Cannot allocate memory") and the process dies (seen on 2
    cores after 21 runs of `bench_mass_loss.py`, 2026-12-07). Call it between runs."""
    import gc

    import jax

    jax.clear_caches()
    gc.collect()


def save_figure(fig, path) -> None:
    """Lay out, write (creating the folder, 130 dpi) and close a matplotlib figure."""
    from pathlib import Path

    import matplotlib.pyplot as plt

    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)


def write_markdown(path, lines: list[str], image: str, alt: str) -> None:
    """Write a results section: ``lines``, then the chart ``image`` (a path relative to the
    markdown file) under ``alt``."""
    from pathlib import Path

    Path(path).write_text("\n".join([*lines, "", f"![{alt}]({image})", ""]) + "\n")


def choices(text: str, known, flag: str) -> list[str]:
    """The comma-separated names of ``text`` (empty items dropped), each checked against
    ``known``; a name not in it exits with a message naming ``flag``."""
    names = [n for n in text.split(",") if n]
    for n in names:
        if n not in known:
            raise SystemExit(f"{flag}: {n!r} is not one of {', '.join(known)}")
    return names


def write_table(path, lines: list[str]) -> None:
    """Write a results file (``lines`` joined, newline-terminated) and print it."""
    from pathlib import Path

    Path(path).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
