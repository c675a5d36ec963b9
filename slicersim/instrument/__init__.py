"""Instrument models: telescope, slicer/MLA spectrograph, H4RG detector, detector-plane mapper."""
