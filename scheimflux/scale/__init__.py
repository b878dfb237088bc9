"""Scale-out over many scans with Dask (`pip install "scheimflux[scale]"`)."""

from ._dask import ScanResult as ScanResult, reconstruct_scans as reconstruct_scans

__all__ = [
    "reconstruct_scans",
    "ScanResult",
]
