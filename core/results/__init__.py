"""Results: the files a classification writes (CSV, GeoJSON, maps, LAS, QGIS style) and their evaluation."""
