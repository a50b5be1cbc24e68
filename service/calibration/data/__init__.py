"""Real data shipped with the calibration methods (seed 003 Table 1), read through
service.io.datasets."""

from pathlib import Path

DATA_DIR = Path(__file__).parent
SEED003_TABLE1 = DATA_DIR / "seed003_table1.csv"
