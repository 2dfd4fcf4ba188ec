"""``python -m bac_ecu_bridge``: see :mod:`bac_ecu_bridge.cli`."""

import sys

from bac_ecu_bridge.cli import main

sys.exit(main())
