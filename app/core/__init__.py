"""The fidotrack vision library: numpy/OpenCV/SciPy only, no web or database code."""
