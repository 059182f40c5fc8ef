"""What every figure of the reports shares: matplotlib without a display, time axes, saving."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402, F401  (after the display-less backend is chosen)
import numpy as np  # noqa: E402

from touchdown_ros.workflows.offline import BagEstimate  # noqa: E402


def seconds(result: BagEstimate) -> np.ndarray:
    """The estimate's stamps as seconds after its first (the drop onset)."""
    stamps = result.estimate.stamps_ns
    return (stamps - stamps[0]) * 1e-9


def save(fig, path: Path) -> Path:
    """Write a figure as PNG and close it."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
