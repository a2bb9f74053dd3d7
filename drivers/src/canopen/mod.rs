//! CANopen (CiA 301) and CiA 402 for the TECO wheel drives: frames, transports (SocketCAN, socketcand, in-process bus), the master, the drive state machine, the differential-drive layer.
