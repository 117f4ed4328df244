"""Planner: segment lengths, the stepped pass's geometry, velocity steps, limits, speed, the
run-up before a velocity step (>= 5 L of the friction model in use), and the layering
(trajectories imports nothing from rig)."""

from __future__ import annotations


def test_trajectories_imports_nothing_from_rig(repo_root):
    import ast
    import subprocess
    import sys

    for path in (repo_root / "trajectories").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            assert not any(n == "rig" or n.startswith("rig.") for n in names), (path, names)
    code = "import sys, trajectories; print(sorted(m for m in sys.modules if m == 'rig' or m.startswith('rig.')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=repo_root, check=True)
    assert out.stdout.strip() == "[]"
