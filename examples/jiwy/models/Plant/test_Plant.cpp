/* test_Plant.cpp - stand-alone run of the Plant fixture (not part of the shared library). */
#include <cstdio>
#include "Plant.h"

int main(void)
{
	Plant model;
	XXDouble u[2] = {0.1, 0.0};
	XXDouble y[2] = {0.0, 0.0};
	model.Initialize(u, y, 0.0);
	while (!model.IsFinished())
		model.Calculate(u, y);
	std::printf("%.17g %.17g\n", y[0], y[1]);
	return 0;
}
