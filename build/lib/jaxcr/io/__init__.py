"""File formats at the edge of jaxcr: images, calibration files, datasets, result files.

Only this package (with ``jaxcr/cli``, ``jaxcr/synth`` writers and ``jaxcr/cli/__init__.py``)
touches files or OpenCV I/O; the jitted core takes arrays and pytrees.
"""
