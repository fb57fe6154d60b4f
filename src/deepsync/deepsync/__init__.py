"""DeepSync core: envelope-detector LTE localization, independent of ROS."""

__version__ = "0.1.0"
