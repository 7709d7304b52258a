"""Files: sessions, results, recovery, safe outputs, and the readers' guards."""
