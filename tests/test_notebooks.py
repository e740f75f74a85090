"""The notebooks of notebooks/ run end to end in quick mode (QUICK = True, small scenes,
outputs in a temporary folder) and their closing physics checks (``assert`` cells) pass.

Each notebook is executed with nbclient in a fresh ``python3`` kernel of the current
interpreter, with ``JAX_PLATFORMS=cpu``. ``JAXGRAN_NOTEBOOKS_FULL=1`` runs them in full mode
instead (paper-size scenes, hours on a CPU; no cell timeout).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOKS_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = [
    "01_quickstart.ipynb",
    "02_single_particle.ipynb",
    "03_oedometer_methods.ipynb",
    "04_bonded.ipynb",
    "05_calibration.ipynb",
    "06_speed_vs_accuracy.ipynb",
]
FULL = os.environ.get("JAXGRAN_NOTEBOOKS_FULL", "") not in ("", "0")
CELL_TIMEOUT_S = None if FULL else 600  # per cell; a quick notebook takes about a minute


def _kernel_manager(folder: Path):
    """A kernel manager for a kernel spec written to ``folder`` that starts
    ``python -m ipykernel_launcher`` with this interpreter, whatever kernel specs the user
    has installed (a ``python3`` spec in ~/.local/share/jupyter may point elsewhere)."""
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import KernelManager

    spec_dir = folder / "kernels" / "jaxgran-tests"
    spec_dir.mkdir(parents=True)
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (jaxgran tests)",
        "language": "python",
    }
    (spec_dir / "kernel.json").write_text(json.dumps(spec))
    ksm = KernelSpecManager(kernel_dirs=[str(folder / "kernels")])
    return KernelManager(kernel_name="jaxgran-tests", kernel_spec_manager=ksm)


def _with_quick(nb, quick: bool):
    """Replace the cell tagged ``parameters`` by ``QUICK = quick``."""
    tagged = [c for c in nb.cells if "parameters" in c.get("metadata", {}).get("tags", [])]
    assert len(tagged) == 1, "a notebook needs exactly one cell tagged 'parameters'"
    assert "QUICK = True" in tagged[0].source, "the parameter cell must default to QUICK = True"
    tagged[0].source = f"QUICK = {quick}  # injected by tests/test_notebooks.py"
    return nb


def test_notebooks_are_stored_without_outputs():
    for name in NOTEBOOKS:
        nb = nbformat.read(NOTEBOOKS_DIR / name, as_version=4)
        nbformat.validate(nb)
        code = [c for c in nb.cells if c.cell_type == "code"]
        assert code[0].get("metadata", {}).get("tags") == ["parameters"], name
        for cell in code:
            assert not cell.outputs and cell.execution_count is None, f"{name}: clear outputs"
        # every notebook ends by checking physical figures
        assert "assert " in code[-1].source, name


def _run_notebook(name: str, tmp_path: Path) -> None:
    nb = _with_quick(nbformat.read(NOTEBOOKS_DIR / name, as_version=4), quick=not FULL)
    env = dict(os.environ)
    env["JAX_PLATFORMS"] = "cpu"
    env["TMPDIR"] = str(tmp_path)  # the notebooks' tempfile outputs land in pytest's folder
    km = _kernel_manager(tmp_path)
    try:
        _execute(nb, name, km, env)
    finally:
        # A client given its kernel manager leaves the kernel running; each kernel holds
        # 0.7-1.8 GB (JAX and the notebook's arrays) until pytest exits.
        if km.has_kernel:
            km.shutdown_kernel(now=True)
    assert not km.is_alive(), f"{name}: the kernel outlived its notebook"


def _execute(nb, name: str, km, env: dict) -> None:
    client = nbclient.NotebookClient(
        nb,
        km=km,
        timeout=CELL_TIMEOUT_S,
        startup_timeout=120,
        allow_errors=False,
        resources={"metadata": {"path": str(NOTEBOOKS_DIR)}},
    )
    from nbclient.exceptions import CellExecutionError

    t0 = time.perf_counter()
    try:
        client.execute(env=env)
    except CellExecutionError as exc:
        pytest.fail(f"{name} failed:\n{exc}")
    finally:
        if client.kc is not None:
            client.kc.stop_channels()
    wall = time.perf_counter() - t0
    code = [c for c in nb.cells if c.cell_type == "code"]
    for cell in code:
        errors = [o for o in cell.get("outputs", []) if o.get("output_type") == "error"]
        assert not errors, f"{name}: {errors[0].get('ename')}: {errors[0].get('evalue')}"
    text = "".join(o.get("text", "") for o in code[-1].get("outputs", []))
    assert "all checks passed" in text, f"{name}: the closing check cell did not finish"
    print(f"{name}: {wall:.1f} s")


# Two classes so that `pytest -n 2 --dist loadscope` (the README's test command) can run the
# two halves on different workers: each notebook runs in its own kernel and shares nothing.
@pytest.mark.slow
class TestNotebooksFirstHalf:
    @pytest.mark.parametrize("name", NOTEBOOKS[:3])
    def test_notebook_runs(self, name, tmp_path):
        _run_notebook(name, tmp_path)


@pytest.mark.slow
class TestNotebooksSecondHalf:
    @pytest.mark.parametrize("name", NOTEBOOKS[3:])
    def test_notebook_runs(self, name, tmp_path):
        _run_notebook(name, tmp_path)
