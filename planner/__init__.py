"""Assignment, sequencing and push paths: layout + environment -> plan.

``plan_assembly(layout, env, options)`` is the entry point; ``Replanner`` recomputes
the remainder during a run; ``check_plan`` replays a plan independently.
"""

from .check import Collision, check_plan
from .core import PlanStats, plan_assembly
from .options import PLANNERS, PlanOptions
from .plan import Assignment, Expect, Operation, Plan, Unfilled, load_plan, plan_from_dict
from .replan import Remainder, Replanner

__all__ = ["PLANNERS", "Assignment", "Collision", "Expect", "Operation", "Plan", "PlanOptions",
           "PlanStats", "Remainder", "Replanner", "Unfilled", "check_plan", "load_plan",
           "plan_assembly", "plan_from_dict"]
