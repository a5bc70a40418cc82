/* xxmodel.c - equations of the ANSI-C JIWY plant fixture (function prefix "plant_").
 * Shape of a 20-sim ANSI-C template export; written for rtloop's tests (MIT). */
#include "xxmodel.h"

XXDouble plant_xx_start_time = 0.0;
XXDouble plant_xx_finish_time = 100.0;
XXDouble plant_xx_step_size = 0.001;
XXDouble plant_xx_time = 0.0;
XXBoolean plant_xx_stop_simulation = XXFALSE;

XXDouble plant_xx_P[14];
XXDouble plant_xx_V[16];
XXDouble plant_xx_s[4];
XXDouble plant_xx_R[4];

void plant_ModelInitialize(void)
{
	int i;
	/* pan: r, Jmot, Dmot, g, b, Jcam, Dcam */
	plant_xx_P[0] = 0.018;
	plant_xx_P[1] = 2.06e-7;
	plant_xx_P[2] = 1.77e-6;
	plant_xx_P[3] = 1.0 / 19.0;
	plant_xx_P[4] = 1.0;
	plant_xx_P[5] = 3e-4;
	plant_xx_P[6] = 2e-4;
	/* tilt */
	plant_xx_P[7] = 0.00701;
	plant_xx_P[8] = 5.28e-8;
	plant_xx_P[9] = 4e-7;
	plant_xx_P[10] = 1.0 / 19.0;
	plant_xx_P[11] = 0.25;
	plant_xx_P[12] = 4.5e-5;
	plant_xx_P[13] = 1e-4;
	for (i = 0; i < 16; i++) plant_xx_V[i] = 0.0;
	for (i = 0; i < 4; i++) { plant_xx_s[i] = 0.0; plant_xx_R[i] = 0.0; }
}

void plant_CalculateDynamic(void)
{
	/* pan */
	plant_xx_V[2] = plant_xx_P[3] * plant_xx_P[4];
	plant_xx_V[3] = plant_xx_P[1] + plant_xx_V[2] * plant_xx_V[2] * plant_xx_P[5];
	plant_xx_V[4] = plant_xx_s[0] / plant_xx_V[3];
	plant_xx_V[5] = plant_xx_V[2] * plant_xx_V[4];
	plant_xx_V[6] = plant_xx_P[6] * plant_xx_V[5];
	plant_xx_R[0] = plant_xx_P[0] * plant_xx_V[0] - plant_xx_P[2] * plant_xx_V[4]
		- plant_xx_V[2] * plant_xx_V[6];
	plant_xx_R[1] = plant_xx_V[5];
	/* tilt */
	plant_xx_V[7] = plant_xx_P[10] * plant_xx_P[11];
	plant_xx_V[8] = plant_xx_P[8] + plant_xx_V[7] * plant_xx_V[7] * plant_xx_P[12];
	plant_xx_V[9] = plant_xx_s[2] / plant_xx_V[8];
	plant_xx_V[10] = plant_xx_V[7] * plant_xx_V[9];
	plant_xx_V[11] = plant_xx_P[13] * plant_xx_V[10];
	plant_xx_R[2] = plant_xx_P[7] * plant_xx_V[1] - plant_xx_P[9] * plant_xx_V[9]
		- plant_xx_V[7] * plant_xx_V[11];
	plant_xx_R[3] = plant_xx_V[10];
}

void plant_CalculateOutput(void)
{
	plant_xx_V[14] = plant_xx_s[1];
	plant_xx_V[15] = plant_xx_s[3];
}
