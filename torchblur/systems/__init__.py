"""Linear time-invariant actuator models and their exact responses to sine and multisine
inputs (``lti``), and 2x2 plants for two-axis mirrors (``mimo``)."""
from torchblur.systems.lti import LTIMultisineTrajectory, LTIResponse, LTISineTrajectory, Plant
from torchblur.systems.mimo import MIMOSineTrajectory, PlantMatrix, plant_from_coefficients

__all__ = ["LTIMultisineTrajectory", "LTIResponse", "LTISineTrajectory", "MIMOSineTrajectory", "Plant", "PlantMatrix", "plant_from_coefficients"]
