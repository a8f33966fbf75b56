"""Classification on a Dask cluster: the same rows as one process, from tiles of the epochs
streamed to disk (`blocks`), described by workers (`tasks`), gathered by the client (`classify`).
"""
