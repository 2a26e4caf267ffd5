"""The data that flows between the stages: plain frozen dataclasses of numpy arrays.

``scene.Scene`` and ``camera.Camera``, ``raybatch.RayBatch`` (and the ray-type names),
``optrace.OpTrace`` (and the op codes), ``hits.Hits``, ``paths.PathTrace`` and
``paths.RectLight``. They hold arrays and convert them (slices, CSR views, counts); each
stage's behaviour lives in its own package. Import them from their modules: this face
stays empty so that a light type (Scene, Camera) does not pull in numba.
"""
