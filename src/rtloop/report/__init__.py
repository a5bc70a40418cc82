"""Figures and an HTML report from run artifacts (``rtloop report``)."""

from .build import Report as Report
from .build import build_report as build_report
from .build import main as main
from .data import Histogram as Histogram
from .data import ReportError as ReportError
from .data import Run as Run
from .data import TaskSeries as TaskSeries
from .data import histogram as histogram
from .data import load_run as load_run
from .data import task_series as task_series

__all__ = ["Histogram", "Report", "ReportError", "Run", "TaskSeries", "build_report", "histogram", "load_run",
           "main", "task_series"]
