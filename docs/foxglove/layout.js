// The layout the page opens: a 3D panel over the map (every scene topic of `muster view`
// shown) and, beside it, the broker's event feed as it arrives.
const laser = (colour) => ({ visible: true, pointSize: 4, colorMode: "flat", flatColor: colour });
const MUSTER_LAYOUT = {
  id: "muster",
  name: "muster",
  permission: "CREATOR_WRITE",
  baseline: {
    savedAt: undefined,
    data: {
      configById: {
        "3D!muster": {
          followTfFrame: "map",
          followMode: "follow-none",
          scene: { enableStats: false, backgroundColor: "#ffffff" },
          cameraState: {
            perspective: true, distance: 46, phi: 26, thetaOffset: 0,
            targetOffset: [20, 10, 0], target: [0, 0, 0], targetOrientation: [0, 0, 0, 1],
            fovy: 45, near: 0.5, far: 5000,
          },
          topics: {
            "/map": {
              visible: true, colorMode: "gradient", colorField: "occupied",
              gradient: ["#f4f4f4ff", "#303030ff"], minValue: 0, maxValue: 100,
            },
            "/robots": { visible: true },
            "/people": { visible: true },
            "/tracks": { visible: true },
            "/plans": { visible: true },
            "/T1/laser": laser("#e6550dff"),
            "/T2/laser": laser("#3182bdff"),
            "/T3/laser": laser("#31a354ff"),
            "/D1/laser": laser("#756bb1ff"),
          },
          layers: {},
          // The robots' frames are in the scene already, as bodies with their names.
          transforms: Object.fromEntries(
            ["map", "T1", "T2", "T3", "D1"].map((f) => [`frame:${f}`, { visible: false }]),
          ),
          publish: { type: "point" },
        },
        "RawMessages!events": { topicPath: "/muster/events", diffEnabled: false },
      },
      globalVariables: {},
      userNodes: {},
      playbackConfig: { speed: 1 },
      layout: { direction: "row", first: "3D!muster", second: "RawMessages!events", splitPercentage: 74 },
    },
  },
  working: undefined,
  syncInfo: undefined,
};
