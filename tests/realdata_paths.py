"""Where the shared real recordings live: ``../shared/realdata`` beside the clone (CI has it
there too; see ``../shared/realdata/README.md``)."""

from pathlib import Path

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
KITCHEN_TUM = REALDATA / "7scenes-kitchen-tum"
MAVLINK_LOGS = REALDATA / "mavlink"
R2R_INSTRUCTIONS = REALDATA / "instructions" / "R2R_val_unseen.json"
