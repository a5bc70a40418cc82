/* xxmain.c - stand-alone run of the ANSI-C fixture (not part of the shared library). */
#include <stdio.h>
#include "xxmodel.h"
#include "xxsubmod.h"

int main(void)
{
	XXDouble u[2] = {0.1, 0.0};
	XXDouble y[2] = {0.0, 0.0};
	plant_XXInitializeSubmodel(u, y, plant_xx_start_time);
	while (!plant_xx_stop_simulation)
		plant_XXCalculateSubmodel(u, y, plant_xx_time);
	plant_XXTerminateSubmodel(u, y, plant_xx_time);
	printf("%.17g %.17g\n", y[0], y[1]);
	return 0;
}
