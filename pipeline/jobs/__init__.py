"""Work in batches: many missions at once on one maps store (:mod:`.missions`,
:func:`pipeline.plan_missions`), the job file (:mod:`.job_file`) and its generated reference
(:mod:`.schema`), a job's run (:mod:`.run`, :func:`pipeline.run_job`) and the kernels' compilation
before its first run (:mod:`.warmup`)."""

from .._lazy import submodules

__getattr__ = submodules(__name__)
