import subprocess
import sys


def test_cli_version():
    out = subprocess.run([sys.executable, "-m", "telefringe.cli", "--version"],
                         capture_output=True, text=True, check=True)
    assert out.stdout.startswith("telefringe ")
