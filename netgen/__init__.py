"""netgen: OpenStreetMap + elevation -> SUMO network and a chunked 3D world."""
__version__ = "0.1.38"
