import sys
from pathlib import Path

# The analytic scene is shared with the pose-graph tests.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "pgo"))
