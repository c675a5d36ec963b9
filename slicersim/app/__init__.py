"""User-facing applications: the ``slicersim`` command line, the demo and plots."""
