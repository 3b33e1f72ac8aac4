"""``python -m securegs_warp.cli``: the ``securegs`` command."""
import sys

from . import main

sys.exit(main())
