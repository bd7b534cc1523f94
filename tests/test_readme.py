"""The README's Python snippet runs as written (a fresh process from the project root, warnings as errors)."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_python_snippet_runs_as_written():
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.DOTALL)
    assert len(blocks) == 1
    result = subprocess.run([sys.executable, "-W", "error::UserWarning", "-c", blocks[0]], cwd=ROOT,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "cfa_layout='RGGB'" in result.stdout  # what the snippet's comment says it prints


CPU_INDEX = "--index-url https://download.pytorch.org/whl/cpu"


def test_the_install_a_cpu_user_copies_asks_for_the_cpu_build_and_ci_runs_command_2():
    """Before: the Quickstart's commands ran `pip install torch==2.13.0`, which fetches the CUDA build (gigabytes)
    wherever the index serves it, as PyPI does on Linux. Every torch install the README gives asks for the CPU
    build; .ci/run runs command 2 as written but for that flag (its own index serves the CPU build)."""
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```\n(.*?)\n```", readme.split("## Install", 1)[1].split("## Python API", 1)[0])
    installs = [command for block in blocks for command in block.split(" && ") if "install" in command and
                "torch" in command]
    assert len(installs) == 3 and all(CPU_INDEX in install for install in installs), installs
    commands = [block for block in blocks if block.startswith("python3 -m venv")]
    assert len(commands) == 2
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line.startswith("pip install")]
    assert ci == [commands[1].split(" && ", 2)[2].replace(f" {CPU_INDEX}", "")]
