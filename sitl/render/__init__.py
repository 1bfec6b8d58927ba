"""The simulated RGB-D camera: an offscreen rasteriser with a D435i-like sensor model.

``renderer.Renderer`` renders frames in-process (lockstep harnesses, datasets); ``server.CameraServer``
streams them over a Unix socket from inside ``sitl serve``; ``config`` holds the camera and scene models
(``VisualConfig`` is a scenario's ``[visual]`` table). Importing this package creates no GL context.
"""
