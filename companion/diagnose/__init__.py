"""Analysis of recordings: the closed-loop diagnosis (``closed_loop``), the sensor-only diagnosis
(``sensor``), the reports, the advice and the fitted model."""
