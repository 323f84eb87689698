"""slidecal.routines.ops: the unattended operations: the verdict, the install store and its lock,
the morning report, the OAK flash, fault injection, ``slidecal check`` and ``slidecal rehearse``."""
