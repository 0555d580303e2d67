"""The Python client of the API, as the service's code and older imports name it: it lives in
``ibr_client.client`` (the ``ibr-client`` distribution, clients/python/), re-exported here."""

from ibr_client.client import (
    ApiError,
    Client,
    FileData,
    InvalidId,
    JobFailed,
    read_dataset_dir,
    with_sha256s,
)

__all__ = ["ApiError", "Client", "FileData", "InvalidId", "JobFailed", "read_dataset_dir", "with_sha256s"]
