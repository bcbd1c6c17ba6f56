"""The build report: a static HTML site a curator browses from disk (see `writer.py` for its layout)."""

from nuplan_occ.report.writer import ReportResult, write_report

__all__ = ["ReportResult", "write_report"]
