"""The ibr-service rendering engine.

Pure arrays in, arrays out. Shared by every worker type. Never imports
``api_schemas``, ``service`` or ``workers`` and never reads the environment.
"""

ENGINE_VERSION = "0.1.0"
