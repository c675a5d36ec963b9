"""Allow ``python -m slicersim``."""

from slicersim.app.cli import main

raise SystemExit(main())
