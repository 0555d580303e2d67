"""The Python client of ibr-service: :class:`Client` (``ibr_client.client``) and the ``ibr`` client
commands (``ibr_client.cli``), on the request and response models of ``api_schemas``.

Installed on its own by the ``ibr-client`` distribution (clients/python/: httpx, pydantic, typer,
rich and numpy; no numba, Embree or OpenImageIO), and part of the service's own install.
"""

from ibr_client.client import ApiError, Client, FileData, InvalidId, JobFailed, read_dataset_dir, with_sha256s

__all__ = ["ApiError", "Client", "FileData", "InvalidId", "JobFailed", "read_dataset_dir", "with_sha256s"]
