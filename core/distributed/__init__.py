"""The classify run and the training set on a Dask cluster: the same rows as one process, from
tiles of the epochs streamed to disk (`blocks`), described by workers (`tasks`), the classify
run's engine on the client (`engine`).
"""
