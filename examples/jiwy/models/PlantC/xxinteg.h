/* xxinteg.h - Euler integration of the ANSI-C fixture (written for rtloop, MIT). */
#ifndef XXINTEG_H
#define XXINTEG_H

void plant_XXEulerStep(void);

#endif
