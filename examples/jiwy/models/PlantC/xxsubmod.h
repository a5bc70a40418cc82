/* xxsubmod.h - submodel interface of the ANSI-C fixture (function prefix "plant_").
 * Written for rtloop (MIT) in the shape of 20-sim's ANSI-C template. */
#ifndef XXSUBMOD_H
#define XXSUBMOD_H

#include "xxtypes.h"

void plant_XXInitializeSubmodel(XXDouble *u, XXDouble *y, XXDouble t);
void plant_XXCalculateSubmodel(XXDouble *u, XXDouble *y, XXDouble t);
void plant_XXTerminateSubmodel(XXDouble *u, XXDouble *y, XXDouble t);

#endif
