"""rig-runtime: real-time control runtime for the 1:5 IRDW roller rig."""

__version__ = "0.1.0"
