/* xxinteg.c - Euler integration of the ANSI-C fixture (written for rtloop, MIT).
 * States move with the rates of the previous evaluation, then time advances. */
#include "xxmodel.h"
#include "xxinteg.h"

void plant_XXEulerStep(void)
{
	int i;
	for (i = 0; i < plant_xx_number_states; i++)
		plant_xx_s[i] = plant_xx_s[i] + plant_xx_R[i] * plant_xx_step_size;
	plant_xx_time = plant_xx_time + plant_xx_step_size;
}
