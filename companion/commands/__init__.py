"""One module per CLI command group; each has ``register(subparsers)``.

Command modules import nothing heavy at module level (torch, cv2, mavsdk, jsbsim): ``companion --help``
must stay instant and the service light. Heavy imports happen inside the handlers.
"""
