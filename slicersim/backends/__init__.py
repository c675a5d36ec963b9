"""Compute backends: the only package that knows OpenCL.  Each kernel family
(``kernels/*.cl``) comes with its NumPy twin; :mod:`~slicersim.backends.dispatch` picks one."""
