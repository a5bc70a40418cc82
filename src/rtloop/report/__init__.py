"""Figures and an HTML report from run artifacts (``rtloop report``)."""

from rtloop.report.build import Report as Report
from rtloop.report.build import build_report as build_report
from rtloop.report.data import Histogram as Histogram
from rtloop.report.data import ReportError as ReportError
from rtloop.report.data import Run as Run
from rtloop.report.data import TaskSeries as TaskSeries
from rtloop.report.data import histogram as histogram
from rtloop.report.data import load_run as load_run
from rtloop.report.data import task_series as task_series

__all__ = ["Histogram", "Report", "ReportError", "Run", "TaskSeries", "build_report", "histogram", "load_run",
           "task_series"]
