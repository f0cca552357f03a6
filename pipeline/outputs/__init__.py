"""Stage 5, what leaves the tool: each mission's files for vehicles and people
(:mod:`.files`), the results catalog (STAC + GeoParquet, :mod:`.catalog`), the plots
(:mod:`.plots`) and the job's self-contained HTML report (:mod:`.report`, its page in
``static/``)."""

from .._lazy import submodules

__getattr__ = submodules(__name__)
