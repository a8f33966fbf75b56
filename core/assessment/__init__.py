"""The classify run: a pre-/post-event pair's buildings graded, one skeleton for every engine
(`run`), what it asks of an engine (`engine`), its folder and record (`record`), the engine of
this process (`in_process`)."""
