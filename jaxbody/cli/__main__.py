"""``python -m jaxbody.cli``: the ``jaxbody`` command."""

import sys

from . import main

sys.exit(main())
