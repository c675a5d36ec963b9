"""OpenCL C sources of the kernels (package data, read by :func:`slicersim.backends.opencl.kernel_source`)."""
