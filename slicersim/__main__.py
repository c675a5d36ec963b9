"""Allow ``python -m slicersim``."""

from slicersim.cli import main

raise SystemExit(main())
