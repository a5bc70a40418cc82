/* xxtypes.h - basic types of the rtloop 20-sim-shaped test fixtures.
 * Written for rtloop (MIT); same shape as a 20-sim C++ export, not a copy of it. */
#ifndef XXTYPES_H
#define XXTYPES_H

typedef double XXDouble;
typedef int XXInteger;
typedef bool XXBoolean;

#endif
