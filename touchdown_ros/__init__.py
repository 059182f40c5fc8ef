"""touchdown_ros: PKBKR + EKF estimation of AMB rotor touchdown on auxiliary bearings."""
__version__ = "0.1.0"
