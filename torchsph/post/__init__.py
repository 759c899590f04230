"""Post-processing: the melt pool, the bead and its sections, PyVista pictures, a cap's contact
angle, the moving point source (``python -m torchsph.post RUN``)."""
