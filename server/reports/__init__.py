"""PDF reports (issue 16, build §4): one per run (`GET /runs/{id}/report.pdf`) and a progress report per
patient over dates (`GET /patients/{id}/progress.pdf`), built with reportlab and matplotlib charts."""
