/* xxmodel.h - model globals of the ANSI-C JIWY plant fixture (function prefix "plant_").
 * Shape of a 20-sim ANSI-C template export; written for rtloop's tests (MIT). */
#ifndef XXMODEL_H
#define XXMODEL_H

#include "xxtypes.h"

extern XXDouble plant_xx_start_time;
extern XXDouble plant_xx_finish_time;
extern XXDouble plant_xx_step_size;
extern XXDouble plant_xx_time;
extern XXBoolean plant_xx_stop_simulation;

extern XXDouble plant_xx_P[];	/* parameters */
extern XXDouble plant_xx_V[];	/* variables */
extern XXDouble plant_xx_s[];	/* states */
extern XXDouble plant_xx_R[];	/* rates */

#define plant_xx_number_states 4

void plant_ModelInitialize(void);
void plant_CalculateDynamic(void);
void plant_CalculateOutput(void);

#endif
