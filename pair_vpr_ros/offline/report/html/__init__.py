"""A replay's report as a folder of web pages (``OUT/report/``), self-contained: opened from disk
in any browser, nothing fetched from the network. `writer.ReportWriter` streams the rows and
images while the replay runs; `page.write_page` writes the page and the labels at the end.
"""

from pair_vpr_ros.offline.report.html.page import PageInputs, write_page
from pair_vpr_ros.offline.report.html.writer import ReportWriter

__all__ = ["PageInputs", "ReportWriter", "write_page"]
