"""Scale-out of the batch commands (docs/scale-out.md): :mod:`~jaxcr.scale.devices` (a frame
batch over all local JAX devices), :mod:`~jaxcr.scale.shards` (``--shard I/N``: deterministic
frame blocks of one job into one output folder, merged by ``jaxcr evaluate``) and
:mod:`~jaxcr.scale.executor` (``--executor local|ray``: chunks of frames as tasks, one results
log written by the driver, exactly once)."""
