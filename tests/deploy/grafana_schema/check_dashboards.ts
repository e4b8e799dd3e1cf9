// Type-checks every provisioned Grafana dashboard (deploy/grafana/dashboards)
// against the Dashboard type of @grafana/schema, the version pinned in
// package-lock.json (the Grafana image's version in docker-compose.yml).
// tests/deploy/grafana_schema_test.py runs `tsc` on this file and fails when a
// dashboard file is not imported here.
import type { Dashboard } from '@grafana/schema';

import behaviorActivity from '../../../deploy/grafana/dashboards/behavior_activity.json';
import fleetOverview from '../../../deploy/grafana/dashboards/fleet_overview.json';
import missions from '../../../deploy/grafana/dashboards/missions.json';
import monitoringActivationTimes from '../../../deploy/grafana/dashboards/monitoring_activation_times.json';
import simulatorPerformance from '../../../deploy/grafana/dashboards/simulator_performance.json';
import vehicleState from '../../../deploy/grafana/dashboards/vehicle_state.json';

// A JSON module types "absolute" as string and 1 as number: widen the schema's
// string enums and literal unions the same way, so that the check is on
// structure, required fields and value types. (The enum values are checked by
// grafana_schema_test.py.)
type Widen<T> = T extends string
  ? string
  : T extends number
    ? number
    : T extends boolean
      ? boolean
      : T extends ReadonlyArray<infer E>
        ? Array<Widen<E>>
        : T extends object
          ? { [K in keyof T]: Widen<T[K]> }
          : T;

// Keys the schema does not know (a misspelt "gridpos") are errors too: a
// JSON module is not a fresh object literal, so tsc would not report them.
// Each object is matched against the schema's object types it fits (a panel
// is a Panel or a RowPanel); free-form maps (options, targets) take any key.
type Fit<A, S> = S extends object ? (A extends S ? S : never) : never;
type Exact<A, S> = unknown extends S
  ? A
  : A extends ReadonlyArray<infer E>
    ? [NonNullable<S>] extends [ReadonlyArray<infer F>]
      ? Array<Exact<E, F>>
      : A
    : A extends object
      ? [Fit<A, S>] extends [never]
        ? A
        : ExactObject<A, Fit<A, S>>
      : A;
type ExactObject<A, S> = S extends object
  ? {
      [K in keyof A]: K extends keyof S
        ? Exact<A[K], S[K]>
        : A[K] extends undefined
          ? A[K]
          : `key "${K & string}" is not in the Grafana dashboard schema`;
    }
  : never;

type Schema = Widen<Dashboard>;

export const behaviorActivityDashboard: Schema = behaviorActivity;
export const behaviorActivityKeys: Exact<typeof behaviorActivity, Schema> = behaviorActivity;
export const fleetOverviewDashboard: Schema = fleetOverview;
export const fleetOverviewKeys: Exact<typeof fleetOverview, Schema> = fleetOverview;
export const missionsDashboard: Schema = missions;
export const missionsKeys: Exact<typeof missions, Schema> = missions;
export const monitoringActivationTimesDashboard: Schema = monitoringActivationTimes;
export const monitoringActivationTimesKeys: Exact<typeof monitoringActivationTimes, Schema> =
  monitoringActivationTimes;
export const simulatorPerformanceDashboard: Schema = simulatorPerformance;
export const simulatorPerformanceKeys: Exact<typeof simulatorPerformance, Schema> = simulatorPerformance;
export const vehicleStateDashboard: Schema = vehicleState;
export const vehicleStateKeys: Exact<typeof vehicleState, Schema> = vehicleState;
