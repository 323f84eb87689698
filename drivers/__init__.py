"""slidecal.drivers: the hardware interfaces (``base``) and the UR, OAK and UVC drivers.

ur-rtde (``slidecal[ur]``) and depthai (``slidecal[oak]``) are optional: importing this package
or a driver module never needs them; a driver imports its library when it is used.
"""
