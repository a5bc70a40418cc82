/* xxtypes.h - basic types of the rtloop ANSI-C 20-sim-shaped fixture (written for rtloop, MIT). */
#ifndef XXTYPES_H
#define XXTYPES_H

typedef double XXDouble;
typedef int XXInteger;
typedef int XXBoolean;
#define XXTRUE 1
#define XXFALSE 0

#endif
