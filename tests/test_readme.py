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
