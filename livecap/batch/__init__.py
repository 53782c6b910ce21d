"""Batch solving of a take library on Dask's distributed scheduler (``livecap batch``, docs/batch.md)."""
