"""Driving pieces shared by the TrackMania pipeline and the built-in simulator.

NumPy only (plus torch for :mod:`tmrl.driving.models`), no game dependency: the trajectory
reward (:mod:`.reward`), the 19-beam lidar (:mod:`.lidar`), observation preprocessors and sample
compressors (:mod:`.preprocessors`, :mod:`.compressors`), the array-shaped memories that rebuild
histories (:mod:`.memories`) and the models (:mod:`.models`). Importing this package imports
none of the submodules.
"""
