"""Imaging workflows (``adseismic image``): the Born operator, reverse-time migration and least-squares RTM
(:mod:`adseismic.imaging.born`) and the run that writes image.h5 and its figures (:mod:`adseismic.imaging.run`)."""
