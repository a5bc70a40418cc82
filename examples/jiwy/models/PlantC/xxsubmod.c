/* xxsubmod.c - submodel functions of the ANSI-C JIWY plant fixture (prefix "plant_").
 * Written for rtloop (MIT) in the shape of 20-sim's ANSI-C template. */
#include "xxmodel.h"
#include "xxinteg.h"
#include "xxsubmod.h"

static void plant_CopyInputsToVariables(XXDouble *u)
{
	plant_xx_V[0] = u[0];	/* SteeringPan */
	plant_xx_V[1] = u[1];	/* SteeringTilt */
}

static void plant_CopyVariablesToOutputs(XXDouble *y)
{
	y[0] = plant_xx_V[14];	/* AnglePan */
	y[1] = plant_xx_V[15];	/* AngleTilt */
}

void plant_XXInitializeSubmodel(XXDouble *u, XXDouble *y, XXDouble t)
{
	plant_xx_time = t;
	plant_xx_stop_simulation = XXFALSE;
	plant_ModelInitialize();
	plant_CopyInputsToVariables(u);
	plant_CalculateDynamic();
	plant_CalculateOutput();
	plant_CopyVariablesToOutputs(y);
}

void plant_XXCalculateSubmodel(XXDouble *u, XXDouble *y, XXDouble t)
{
	(void)t;	/* time is internal: every call advances one step */
	if (plant_xx_stop_simulation) {
		plant_CopyVariablesToOutputs(y);
		return;
	}
	plant_CopyInputsToVariables(u);
	plant_XXEulerStep();
	plant_CalculateDynamic();
	plant_CalculateOutput();
	plant_CopyVariablesToOutputs(y);
	if (plant_xx_finish_time > 0.0
		&& plant_xx_time >= plant_xx_finish_time - 0.5 * plant_xx_step_size)
		plant_xx_stop_simulation = XXTRUE;
}

void plant_XXTerminateSubmodel(XXDouble *u, XXDouble *y, XXDouble t)
{
	(void)t;
	plant_CopyInputsToVariables(u);
	plant_CopyVariablesToOutputs(y);
	plant_xx_stop_simulation = XXTRUE;
}
