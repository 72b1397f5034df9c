"""File formats at the edge of jaxcr: images, calibration files, datasets, result files.

Only this package (with ``jaxcr/commands``, ``jaxcr/synth`` writers and ``jaxcr/cli.py``)
touches files or OpenCV I/O; the jitted core takes arrays and pytrees.
"""
