"""The paper's Table II baselines as benchmark methods, on the same simulated VLM as OnFly.

=================  =====================================================================
name               method
=================  =====================================================================
``typefly``        :mod:`onfly.baselines.typefly`: skill programs over a simulated detector
``pivot``          :mod:`onfly.baselines.pivot`: iterative visual prompting with arrows
``spf``            :mod:`onfly.baselines.spf`: point + travel distance, yaw then straight line
``spf_planner``    the same SPF goals flown through OnFly's ESDF + MPC (planner control study)
=================  =====================================================================

Each gets exactly the stop interface the OnFly paper added (a ``stop`` skill, ``{"stop":
true}``, depth 0) and nothing else of OnFly's machinery. Importing this package registers them.
"""

from onfly.baselines.pivot import make_pivot
from onfly.baselines.spf import make_spf, make_spf_planner
from onfly.baselines.typefly import make_typefly
from onfly.bench.registry import register

__all__ = ["make_typefly", "make_pivot", "make_spf", "make_spf_planner"]

register("typefly", make_typefly, replace=True)
register("pivot", make_pivot, replace=True)
register("spf", make_spf, replace=True)
register("spf_planner", make_spf_planner, replace=True)
